"""Every reference the docs, the notebooks and the code's comments make still holds.

A renamed file, heading, flag or function leaves its old name behind in prose that no other
test reads; a user then follows a dead link or types a command that no longer parses. Here
each repository path and markdown link exists, each `docs/NAME.md, "Heading"` citation names a
heading of that file, each `xvoe ...` command parses with the real parser (nothing is run),
each `python benchmarks/X.py --flag` names a flag the script takes, each `xvoe.NAME`
resolves (`viz.NAME` never does: there is no xvoe.viz), and each --flag prose names is taken by
an xvoe verb, a script of the repository or a tool the finder lists. docs/log/ is history and not read.
The finding and checking is in tests/doc_references.py.
"""
from __future__ import annotations

import doc_references as refs
import pytest

GROUPS = {
    "README and docs": lambda where: where == "README.md" or where.startswith("docs/"),
    "notebooks": lambda where: where.startswith("notebooks/"),
    "code comments and docstrings": lambda where: where.endswith(".py"),
}


@pytest.mark.parametrize("group", sorted(GROUPS))
def test_no_dead_references(group):
    texts = [text for text in refs.repository_texts() if GROUPS[group](text.where)]
    assert texts, f"no {group} found: the test reads nothing"
    dead = refs.dead_references(texts)
    if dead:
        pytest.fail(f"{len(dead)} dead references in the {group}:\n" + "\n".join(map(str, dead)), pytrace=False)


def test_every_text_belongs_to_a_group():
    assert all(any(belongs(text.where) for belongs in GROUPS.values()) for text in refs.repository_texts())


def reported(texts: list[refs.Text]) -> set[tuple[str, str]]:
    return {(dead.where, " ".join(dead.reference.split())) for dead in refs.dead_references(texts)}


def test_planted_dead_references_are_reported_at_their_lines():
    heading = sorted(refs.headings(refs.ROOT / "docs" / "decisions.md"))[0]
    planted = f"""# A page with a dead reference of every kind, each after a live one

The figures are in `docs/results.md` and [the models](models.md); see docs/no-such-file.md
and [gone](no-such-page.md).
As docs/decisions.md, "{heading}" and "No such heading" say,
and docs/decisions.md "Not a
heading either"; docs/results.md ("Nor this") and docs/log/speed.md, "Nor that in the log".

```
xvoe train plato --data run/latents-train.h5 --out RUN --seed S   # placeholders parse
xvoe train --stage plato --out run
xvoe score --model xpl --data test.h5 --out a.csv; xvoe metrics a.csv --out report --rounds many
xvoe show ... --out pair.mp4
python benchmarks/steps.py --threads 1 --recipe cpu | tail -3
python benchmarks/steps.py --no-such-flag
```

Mentions may leave arguments out: `xvoe score`, `xvoe score --shard`, `xvoe train xpl|plato`,
but not name what is gone: `xvoe generate --preset paper`, `python -m xvoe trian`.
`xvoe.score(...)` and `xvoe.custom.make_pair` resolve; `viz.true_objects`, `xvoe.viz.show`,
`xvoe.no_such_name` and `xvoe.custom.no_such_name` do not. DESIGN section 6 is not here, nor
NOTES-38.md.
Flags in prose: --particles, --times and pytest's --durations are taken; --no-residual is gone.
"""
    texts = refs.markdown_texts(planted, refs.ROOT / "docs" / "planted.md", "docs/planted.md")
    assert reported(texts) == {
        ("docs/planted.md:3", "docs/no-such-file.md"),
        ("docs/planted.md:4", "no-such-page.md"),
        ("docs/planted.md:5", 'docs/decisions.md, "No such heading"'),
        ("docs/planted.md:6", 'docs/decisions.md, "Not a heading either"'),
        ("docs/planted.md:7", 'docs/results.md, "Nor this"'),
        ("docs/planted.md:7", 'docs/log/speed.md, "Nor that in the log"'),
        ("docs/planted.md:11", "xvoe train --stage plato --out run"),
        ("docs/planted.md:12", "xvoe metrics a.csv --out report --rounds many"),
        ("docs/planted.md:15", "python benchmarks/steps.py --no-such-flag"),
        ("docs/planted.md:19", "xvoe generate --preset paper"),
        ("docs/planted.md:19", "python -m xvoe trian"),
        ("docs/planted.md:20", "viz.true_objects"),
        ("docs/planted.md:20", "xvoe.viz.show"),
        ("docs/planted.md:21", "xvoe.no_such_name"),
        ("docs/planted.md:21", "xvoe.custom.no_such_name"),
        ("docs/planted.md:21", "DESIGN section 6"),
        ("docs/planted.md:22", "NOTES-38.md"),
        ("docs/planted.md:23", "--no-residual"),
    }
    message = "\n".join(map(str, refs.dead_references(texts)))
    assert "docs/planted.md:3: 'docs/no-such-file.md': no such file or directory" in message
    assert "unrecognized arguments: --stage" in message
    assert "benchmarks/steps.py takes no --no-such-flag" in message


def test_planted_dead_references_in_python_comments_and_docstrings(tmp_path):
    module = tmp_path / "module.py"
    module.write_text('''"""A module.

Its figures: `xvoe.viz.plot_surprise_curves`, drawn from xvoe/scenes/no_such.py.
"""


def f():
    """Scored by `xvoe score --model xpl --data t.h5 --out s.csv --surprise mse2`."""
    return 1    # why: docs/decisions.md, "A heading that
                # no longer exists"


def g():
    """Scored with --particles 64, not with --no-such-option (its command's, `xvoe score --no-such-option`)."""
    return 2    # --seed, not --sed
''')
    assert reported(refs.python_texts(module)) == {
        (f"{module}:3", "xvoe.viz.plot_surprise_curves"),
        (f"{module}:3", "xvoe/scenes/no_such.py"),
        (f"{module}:8", "xvoe score --model xpl --data t.h5 --out s.csv --surprise mse2"),
        (f"{module}:9", 'docs/decisions.md, "A heading that no longer exists"'),
        (f"{module}:14", "--no-such-option"),
        (f"{module}:14", "xvoe score --no-such-option"),
        (f"{module}:15", "--sed"),
    }
