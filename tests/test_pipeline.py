"""A tiny end-to-end pipeline: a dozen videos, a few steps per stage; and its resumption."""
from dataclasses import replace

import pytest

import xvoe
from xvoe.apps import pipeline
from xvoe.apps.pipeline import PipelineConfig, Stages, compare_models, run_pipeline
from xvoe.errors import XvoeError
from xvoe.inference.model import InferenceConfig
from xvoe.inference.score import reference_nll
from xvoe.scenes import store
from xvoe.training.checkpoints import load_checkpoint
from xvoe.training.config import TrainConfig
from xvoe.training.recipes import DEFAULT_RECIPE, RECIPES


@pytest.fixture
def tiny_cpu_recipe(monkeypatch):
    cpu = RECIPES[DEFAULT_RECIPE]
    few = TrainConfig(steps=6, batch_size=8, warmup_steps=1, log_every=2)
    tiny = replace(cpu, perception=replace(cpu.perception, latent_dim=8, cnn_channels=(8, 8), cnn_hidden=16,
                                           decoder_channels=8),
                   perception_train=few,
                   xpl=replace(cpu.xpl, reasoning=replace(cpu.xpl.reasoning, width=16, layers=1, heads=2, mlp=16),
                               dynamics=replace(cpu.xpl.dynamics, hidden=16, lstm=16, buffer_heads=2)),
                   xpl_train=replace(few, batch_size=4), proposal_train=replace(few, batch_size=4),
                   plato_train=replace(few, batch_size=4),
                   phases=(("plato", replace(few, batch_size=4, steps=9, focus_group="continuity", focus_share=0.5)),))
    monkeypatch.setitem(RECIPES, DEFAULT_RECIPE, tiny)


def test_tiny_pipeline_runs_end_to_end_and_skips_done_stages(tmp_path, tiny_cpu_recipe):
    config = PipelineConfig(str(tmp_path / "run"), train_videos=24, pairs=2, models=("xpl", "plato", "random"),
                            workers=1, progress=False, train_processes=2)
    report = run_pipeline(config)
    run = tmp_path / "run"
    text = report.read_text()
    # the XPL and PLATO stages trained in two processes, each phase of PLATO too; the perception in one
    assert all(load_checkpoint(run / f"{stage}.pt")["world"] == 2 for stage in ("xpl", "proposal", "plato"))
    assert load_checkpoint(run / "perception.pt")["world"] == 1
    assert "Holistic" in text and "| collision |" in text and "continuity S3" in text
    assert text.count("- split: seed") == 3 and "checkpoint_hash" in text     # each score file's header
    for model in ("xpl", "plato", "random"):
        assert (run / "scores" / f"{model}.csv").exists()
    for figure in ("holistic.png", "comparative.png", "components-plato.png", "explanation-blocking-S2.png"):
        assert (run / "report" / figure).exists()
    assert (run / "proposal.pt").exists() and "train-proposal" in text
    plato = load_checkpoint(run / "plato.pt")        # the recipe's later phase, resumed from the first
    assert "train-plato-2" in text and plato["step"] == 9 and plato["train"]["focus_group"] == "continuity"
    stamp = (run / "xpl.pt").stat().st_mtime_ns
    scored = (run / "scores" / "xpl.csv").stat().st_mtime_ns
    run_pipeline(config)                     # everything done: nothing is redone
    assert (run / "xpl.pt").stat().st_mtime_ns == stamp
    assert (run / "scores" / "xpl.csv").stat().st_mtime_ns == scored
    # a phase added to the recipe since: PLATO trains on and is scored again, the report redone; XPL is not
    plato_scored, metrics = ((run / name).stat().st_mtime_ns for name in ("scores/plato.csv", "report/metrics.csv"))
    tiny = RECIPES[DEFAULT_RECIPE]
    RECIPES[DEFAULT_RECIPE] = replace(tiny, phases=(*tiny.phases, ("plato", replace(tiny.phases[0][1], steps=11))))
    run_pipeline(config)
    assert load_checkpoint(run / "plato.pt")["step"] == 11
    assert (run / "scores" / "plato.csv").stat().st_mtime_ns != plato_scored
    assert (run / "report" / "metrics.csv").stat().st_mtime_ns != metrics
    assert (run / "scores" / "xpl.csv").stat().st_mtime_ns == scored
    # fewer models: the report is redone for them, the trained models are not
    run_pipeline(replace(config, models=("xpl", "random")))
    assert (run / "xpl.pt").stat().st_mtime_ns == stamp
    assert {row.split(",")[0] for row in open(run / "report" / "metrics.csv").read().split()[1:]} == {"xpl", "random"}
    assert not (run / "report" / "components-plato.png").exists()           # no figure of a dropped model
    assert "components-plato" not in (run / "report.md").read_text()
    assert (run / "report" / "components-xpl.png").exists()
    assert (run / "report" / "explanation-blocking-S2.png").exists()

    # the Pyro model's surprise beside the paper's, on the same run
    import csv

    out = xvoe.score(str(run / "xpl.pt"), str(run / "data" / "test.h5"), str(tmp_path / "both.csv"),
                      surprise="both", particles=4, progress=False)
    rows = list(csv.DictReader(open(out)))
    assert {"nll", "ess", "p_hidden"} <= set(rows[0])
    assert all(1.0 <= float(r["ess"]) <= 4.0 + 1e-9 and 0.0 <= float(r["p_hidden"]) <= 1.0 for r in rows)
    # the excess: the paper's score less the perception's own error of what it saw, per frame
    import numpy as np

    curves = np.load(out.path.with_suffix(".curves.npz"))
    np.testing.assert_allclose([float(r["s_rec"]) for r in rows], curves["s_rec"].sum(1), rtol=1e-6)
    np.testing.assert_allclose([float(r["excess"]) for r in rows],
                               (curves["s_img"] - curves["s_rec"] + curves["s_dyn"]).sum(1), rtol=1e-5, atol=1e-3)
    assert all(0 <= float(r["s_rec"]) for r in rows) and any(float(r["s_rec"]) > 0 for r in rows)
    assert "excess" in {r.split(",")[2] for r in open(run / "report" / "metrics.csv").read().split()[1:]}
    # both MSE definitions: the default verdict, the better of the proposal and nothing hidden, is
    # never above the paper's, which always takes the proposal
    np.testing.assert_allclose([float(r["paper_score"]) for r in rows],
                               (curves["paper_s_img"] + curves["paper_s_dyn"]).sum(1), rtol=1e-6)
    assert all(float(r["score"]) <= float(r["paper_score"]) * (1 + 1e-6) for r in rows)
    # the NLL's excess: less the NLL of a reference drawing only what was seen

    with store.open_dataset(run / "data" / "test.h5") as file:
        size = file["rgbd"].shape[2]
    reference = reference_nll(curves["s_rec"], 4 * size * size, InferenceConfig().pixel_sigma)
    np.testing.assert_allclose([float(r["nll_excess"]) for r in rows], [float(r["nll"]) for r in rows] - reference,
                               rtol=1e-9, atol=1e-6)
    with pytest.raises(XvoeError, match="NLL surprise needs"):
        xvoe.score(str(run / "plato.pt"), str(run / "data" / "test.h5"), str(tmp_path / "x.csv"),
                    surprise="nll", progress=False)


def test_pipeline_refuses_unknown_models():
    with pytest.raises(XvoeError, match="unknown model"):
        PipelineConfig("x", models=("xpl", "phydnet2"))


def test_report_compares_models_with_their_numbers():
    def row(model, scenario, setting, value, low=0.0, high=1.0):
        return {"metric": "comparative", "model": model, "scenario": scenario, "setting": setting,
                "value": value, "low": low, "high": high}

    rows = [row("xpl", "collision", "S3", 0.9), row("plato", "collision", "S3", 0.4),
            row("xpl", "collision", "S1", 0.97), row("plato", "collision", "S1", 0.8),
            row("random", "collision", "S1", 0.55, 0.45, 0.62), row("random", "collision", "S3", 0.3, 0.2, 0.4)]
    lines = compare_models(rows)
    assert "- collision S3 (explicative): XPL 90.0% beats plato 40.0% (+50.0 points)." in lines
    assert "- plato: lowest predictive (S1) accuracy 80.0% (collision)." in lines
    assert "- random: 50% lies inside the 95% interval in 1 of 2 settings." in lines
    assert compare_models([row("xpl", "collision", "S3", 0.9)]) == []


def test_models_trained_side_by_side_match_one_after_another(tmp_path, tiny_cpu_recipe, monkeypatch):
    """--jobs 2 trains xpl and plato in two processes (the tiny recipe goes with them), then
    scores them; --jobs 1 with as many threads, one after the other: the same bytes. The second
    run starts from the first's data, perception and cache."""
    import os
    import shutil

    import torch

    runs, threads = {}, torch.get_num_threads()
    lane_threads = max(1, len(os.sched_getaffinity(0)) // 2)     # what each of two lanes gets
    for jobs in (1, 2):
        config = PipelineConfig(str(tmp_path / f"jobs{jobs}"), train_videos=8, pairs=1,
                                models=("xpl", "plato", "random"), workers=1, progress=False, jobs=jobs,
                                train_processes=1)
        if jobs == 2:
            shutil.copytree(runs[1] / "data", tmp_path / "jobs2" / "data")
            for name in ("perception.pt", "latents-train.h5"):
                shutil.copy(runs[1] / name, tmp_path / "jobs2" / name)
            (tmp_path / "jobs2" / ".done").mkdir()
            for stage in ("generate-train", "generate-test", "perception", "encode-train"):
                shutil.copy(runs[1] / ".done" / stage, tmp_path / "jobs2" / ".done" / stage)
        with monkeypatch.context() as patch:
            if jobs == 1:       # the training stages take their threads from OMP_NUM_THREADS
                patch.setenv("OMP_NUM_THREADS", str(lane_threads))
            torch.set_num_threads(lane_threads)     # scoring, in this process either way, from torch
            try:
                run_pipeline(config)
            finally:
                torch.set_num_threads(threads)
        runs[jobs] = tmp_path / f"jobs{jobs}"
    for model in ("plato", "xpl"):
        one, two = (torch.load(runs[j] / f"{model}.pt", weights_only=True)["model"] for j in (1, 2))
        assert all(torch.equal(two[name], value) for name, value in one.items()), model
        assert (runs[1] / "scores" / f"{model}.csv").read_bytes() == (runs[2] / "scores" / f"{model}.csv").read_bytes()
    with pytest.raises(XvoeError, match="--jobs"):
        PipelineConfig("x", jobs=-1)


def test_an_interrupted_stage_reports_its_whole_time_when_resumed(tmp_path, monkeypatch):
    """5 s before Ctrl-C and 7 s after the rerun: the stage's marker says 12 s, not 7."""
    clock = iter([100.0, 105.0, 200.0, 207.0, 300.0, 300.0])
    monkeypatch.setattr(pipeline.time, "monotonic", lambda: next(clock))
    stages = Stages(tmp_path, progress=False)

    def interrupted() -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        stages.run("train-x", interrupted)
    assert not stages.done("train-x")
    stages.run("train-x", lambda: None)
    assert (tmp_path / ".done" / "train-x").read_text() == "12.0 s\n"
    assert not (tmp_path / ".partial" / "train-x").exists()
    stages.run("report", lambda: None, key="xpl, random")        # a marker that holds a key too
    assert pipeline.stage_times(tmp_path) == {"report": 0.0, "train-x": 12.0}
