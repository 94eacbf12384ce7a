"""The scene at a display size: the same video simulated again, exact against the stored one,
and the figures that draw it above the model's frames with the explanation onto it."""
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

import xvoe
from xvoe.apps.explanation_figure import OUTLINE_COLORS, explanation_overlay, plot_explanation
from xvoe.apps.frames import save_gif, sheet_rows
from xvoe.cli import main
from xvoe.errors import XvoeError
from xvoe.evaluation.explain import Explanation
from xvoe.scenes import custom, store
from xvoe.scenes.display import _LENGTHS, display_video, enlarge, hidden_silhouettes, outline
from xvoe.scenes.generate import GenerateConfig, generate
from xvoe.scenes.render import STATE_COLUMNS


@pytest.fixture(scope="module")
def splits(tmp_path_factory):
    """One pair per setting at the model's 32x32 and the same seed at 128x128, and a shard."""
    root = tmp_path_factory.mktemp("display")
    made = {size: generate(GenerateConfig("test", pairs=1, size=size, seed=7), root / f"t{size}.h5",
                           progress=False) for size in (32, 128)}
    made["shard"] = generate(GenerateConfig("test", pairs=1, size=32, seed=7), root / "shard.h5", shard=(1, 2),
                             progress=False)
    return made


def test_the_display_is_the_split_rendered_again_at_its_size(splits):
    """To the bit: the frames and ids of the same seed generated at 128x128."""
    with store.open_dataset(splits[32]) as small, store.open_dataset(splits[128]) as large:
        for index in range(0, small["rgbd"].shape[0], 5):
            display = display_video(small, index, 128)
            assert display.resimulated and display.rgbd.shape == (15, 128, 128, 4)
            assert display.ids.shape == (15, 128, 128)
            np.testing.assert_array_equal(display.rgbd, large["rgbd"][index])
            np.testing.assert_array_equal(display.ids, large["ids"][index])


def test_the_display_downsampled_is_the_stored_video(splits):
    """The states are the stored ones times four (lengths) and the same (the rest); every
    4x4 block of one id and one colour is the stored pixel there, and such blocks are most."""
    with store.open_dataset(splits[32]) as file:
        uniform = []
        for index in range(file["rgbd"].shape[0]):
            display, stored = display_video(file, index, 128), file["states"][index]
            again = display_video(file, index, 128)
            np.testing.assert_array_equal(display.rgbd, again.rgbd)        # deterministic
            for name in STATE_COLUMNS:
                column = STATE_COLUMNS.index(name)
                factor = 4 if name in _LENGTHS else 1
                np.testing.assert_array_equal(display.states[..., column], stored[..., column] * factor)
            blocks = display.ids.reshape(15, 32, 4, 32, 4)
            colours = display.rgbd[..., :3].reshape(15, 32, 4, 32, 4, 3)
            one = ((blocks == blocks[:, :, :1, :, :1]).all(axis=(2, 4))
                   & (colours == colours[:, :, :1, :, :1]).all(axis=(2, 4, 5)))
            np.testing.assert_array_equal(blocks[:, :, 0, :, 0][one], file["ids"][index][one])
            np.testing.assert_array_equal(colours[:, :, 0, :, 0][one], file["rgbd"][index][..., :3][one])
            uniform.append(one.mean())
        assert np.mean(uniform) > 0.9


def test_a_shard_is_drawn_from_its_own_units(splits):
    with store.open_dataset(splits["shard"]) as shard, store.open_dataset(splits[128]) as whole:
        first = int(shard.attrs["first_unit"]) * 2
        display = display_video(shard, 3, 128)
        assert display.resimulated
        np.testing.assert_array_equal(display.rgbd, whole["rgbd"][first + 3])


def test_a_hand_made_event_is_enlarged_pixel_by_pixel(tmp_path):
    pair = xvoe.custom.make_pair([xvoe.custom.ball(8, vx=50), xvoe.custom.cube(36, fixed=True),
                                  xvoe.custom.wall(34, half_width=12, height=18)],
                                 xvoe.custom.pass_through(0, 1), wall="S3")
    with store.open_dataset(pair.save(tmp_path / "mine.h5", size=32)) as file:
        display = display_video(file, 1, 128)
        assert not display.resimulated and display.rgbd.shape == (15, 128, 128, 4)
        np.testing.assert_array_equal(display.rgbd[:, 1::4, 2::4], file["rgbd"][1])
        np.testing.assert_array_equal(display.ids[:, 3::4, ::4], file["ids"][1])
        # the sheet draws no "scene 128x128" row of what are the model's frames enlarged
        labels = [tick.get_text() for tick in xvoe.show_video(file, 1).axes[0].get_yticklabels()]
        assert labels == ["model's 32x32", "depth", "ids"] * 2


def test_enlarge_and_outline():
    pictures = np.arange(2 * 3 * 3 * 1, dtype=np.uint8).reshape(2, 3, 3, 1)
    large = enlarge(pictures, 6)
    assert large.shape == (2, 6, 6, 1)
    np.testing.assert_array_equal(large, pictures.repeat(2, axis=1).repeat(2, axis=2))
    assert enlarge(pictures, 5).shape == (2, 5, 5, 1)
    mask = np.zeros((8, 8), bool)
    mask[1:7, 1:7] = True
    edge = outline(mask, width=2)
    assert edge.sum() == 36 - 4 and not edge[3:5, 3:5].any() and edge[1, 1] and not edge[0, 0]


def test_the_never_seen_objects_stand_where_the_states_say(splits):
    """Blocking S2: member 0's cube (8 world units a side, 16 pixels at 128x128) is never
    seen, and stands in every frame; member 1 has none."""
    with store.open_dataset(splits[32]) as file:
        first, second = xvoe.find_pair(file, "blocking", "S2", 0)
        hidden = hidden_silhouettes(file, first, display_video(file, first, 128))
        assert ((15 ** 2 <= hidden.sum(axis=(1, 2))) & (hidden.sum(axis=(1, 2)) <= 17 ** 2)).all()
        assert not hidden_silhouettes(file, second, display_video(file, second, 128)).any()


def test_the_sheet_and_the_gif_draw_the_scene_above_the_model_frames(splits, tmp_path):
    with store.open_dataset(splits[32]) as file:
        rows = sheet_rows(file["rgbd"][0], file["ids"][0], display_video(file, 0, 64).rgbd)
        assert [name for name, _ in rows] == ["scene 64x64", "model's 32x32", "depth", "ids"]
        assert all(row.shape == (15, 64, 64, 3) for _, row in rows)
        np.testing.assert_array_equal(rows[1][1][:, ::2, ::2], file["rgbd"][0][..., :3])
        gif = save_gif(file, 0, tmp_path / "pair.gif", display_size=96)
        plain = save_gif(file, 0, tmp_path / "plain.gif", display_size=None, zoom=2)
    # a caption line of 14 pixels above the columns and above each member
    assert Image.open(gif).size == (4 * 96, 3 * 14 + 2 * 96) and Image.open(plain).size == (3 * 64, 3 * 14 + 2 * 64)
    assert main(["show", str(splits[32]), "--index", "2", "--display-size", "64", "--out",
                 str(tmp_path / "s.png")]) == 0


def test_the_explanation_is_drawn_onto_the_scene():
    """The decoded object (an 8x8 square at 32x32) is half-blended in and outlined in magenta
    where its enlarged picture stands; the true object's outline, a pixel outside it, is dashed
    black and white."""
    frames = 3
    hidden = np.full((frames, 32, 32, 4), 255, np.uint8)
    hidden[:, 8:16, 8:16] = (200, 0, 0, 0)
    truth = np.zeros((frames, 128, 128), bool)
    truth[:, 80:100, 80:100] = True
    scene = np.full((frames, 128, 128, 4), 100, np.uint8)
    explanation = Explanation(scene[:, ::4, ::4], scene[:, ::4, ::4], hidden, 2, "t", display=scene,
                              true_hidden=truth)
    drawn, colour = explanation_overlay(explanation)
    assert drawn.shape == (frames, 128, 128, 3) and colour == "magenta"   # the first of the farthest from grey
    assert (drawn[:, 40, 40] == (150, 50, 50)).all()                   # inside: half the object's colour
    magenta = (drawn[:, :, 40] == OUTLINE_COLORS["magenta"]).all(axis=-1)   # down column 40: the square's edge,
    assert magenta[:, 28:34].any(axis=1).all() and magenta[:, 60:68].any(axis=1).all()   # enlarged four times
    assert not magenta[:, 36:58].any() and not magenta[:, :26].any()
    assert (drawn[:, 10, 10] == 100).all()                              # elsewhere the scene
    assert (drawn[:, 79, 80:100] == 100).all()                          # a pixel's gap round the true object,
    edge = drawn[:, 78, 80:100]                                          # then its outline
    assert {tuple(c) for c in edge.reshape(-1, 3)} == {(0, 0, 0), (255, 255, 255)}
    assert (drawn[:, 90, 90] == 100).all() and (drawn[:, 80, 80] == 100).all()
    nothing, colour = explanation_overlay(Explanation(scene[:, ::4, ::4], scene[:, ::4, ::4], hidden, -1, "t",
                                                      display=scene))
    np.testing.assert_array_equal(nothing, scene[..., :3])              # no slot explained: the scene alone
    assert colour is None
    figure = plot_explanation(explanation)
    assert len(figure.axes) == 1 and figure.drawn_rows[0][1].startswith("scene 128x128")
    # a hand-made event's display is its 32x32 frames enlarged, and is called that
    enlarged = plot_explanation(replace(explanation, display_resimulated=False))
    assert enlarged.drawn_rows[0][1].startswith("model's 32x32,\nenlarged")
    assert "observed" not in [kind for kind, _ in enlarged.drawn_rows]     # the scene row is that row already


def test_a_display_size_outside_its_domain_is_refused(splits, tmp_path):
    """Before any work (the command line's refusals: tests/test_bad_input.py)."""
    with store.open_dataset(splits[32]) as file, pytest.raises(XvoeError, match="display size must be"):
        display_video(file, 0, 8)
    with pytest.raises(XvoeError, match="display size must be"):
        xvoe.show(splits[32], 0, tmp_path / "s.png", display_size=1000)
    with pytest.raises(XvoeError, match="display size must be"):
        xvoe.explain("no-such-model", splits[32], 0, display_size=0)
    assert not (tmp_path / "s.png").exists()


def test_a_split_that_cannot_be_drawn_anew_shows_no_scene_row(tmp_path):
    """A hand-made pair has no seed to simulate again: its stored 32 px frames, enlarged, are the
    model's row already, so no row is labelled as the scene at 128x128; a generated split's is."""
    things = [custom.ball(4, vx=50.0), custom.ball(34), custom.wall(32, half_width=12, height=18)]
    mine = custom.make_pair(things, custom.pass_through(0, 1)).save(tmp_path / "mine.h5", size=32)
    generated = generate(GenerateConfig("test", pairs=1, size=32, seed=2), tmp_path / "g.h5", progress=False)
    labels = {}
    for name, path in (("mine", mine), ("generated", generated)):
        with store.open_dataset(path) as file:
            figure = xvoe.show_video(file, 0, display_size=128)
            labels[name] = {tick.get_text() for tick in figure.axes[0].get_yticklabels()}
    assert "scene 128x128" in labels["generated"] and "model's 32x32" in labels["generated"]
    assert not any(label.startswith("scene") for label in labels["mine"]) and "model's 32x32" in labels["mine"]
