"""The package as a user installs it: a wheel built from the sources, with the shipped weights,
installed into a fresh venv, runs `xvoe generate`, `score --model random` and `metrics` from a
directory that holds no source. Both distributions carry the licence; the inference layer
installs as xvoe.inference, no top-level package but xvoe."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SOURCES = ("setup.cfg", "pyproject.toml", "README.md", "LICENSE", "xvoe", "inference")


def build_wheel(target: Path) -> tuple[Path, Path]:
    """An sdist of a copy of the sources and a wheel built from that sdist (so the sdist must hold
    all a build needs), offline with this venv's setuptools (no isolation: an isolated build would
    fetch setuptools from the network); both must pass `twine check`."""
    pytest.importorskip("build", reason="the dev extras' `build` is not installed")
    pytest.importorskip("twine", reason="the dev extras' `twine` is not installed")
    source = target / "source"
    source.mkdir()
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, source / name, symlinks=True,      # xvoe/inference stays a link
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(ROOT / name, source / name)
    done = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--skip-dependency-check",
                           "--outdir", str(target / "dist"), str(source)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot build a wheel here: {done.stderr.strip().splitlines()[-1:]}")
    built = [next((target / "dist").glob(pattern)) for pattern in ("xvoe-*.tar.gz", "xvoe-*.whl")]
    subprocess.run([sys.executable, "-m", "twine", "check", "--strict", *map(str, built)], check=True,
                   capture_output=True)
    return built[0], built[1]


def fresh_venv(where: Path) -> Path:
    """A venv without xvoe that sees this venv's packages (torch, pyro...) through a .pth line: a
    plain path, so this venv's editable xvoe (installed by a .pth import) stays out of it."""
    venv.create(where, with_pip=False)
    python = where / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib, "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


class Installed:
    """The wheel installed into a fresh venv, and a way to run its commands from a folder that
    holds no source."""

    def __init__(self, root: Path):
        self.root = root
        self.sdist, self.wheel = build_wheel(root)
        self.python = fresh_venv(root / "venv")
        subprocess.run([sys.executable, "-m", "pip", "--python", str(self.python), "install", "--quiet", "--no-deps",
                        "--no-index", str(self.wheel)], check=True, capture_output=True)
        self.env = {**os.environ, "OMP_NUM_THREADS": "1"}
        self.env.pop("PYTHONPATH", None)

    def run(self, work: Path, *args: str) -> str:
        done = subprocess.run([str(self.python.parent / args[0]), *args[1:]], cwd=work, env=self.env,
                              capture_output=True, text=True)
        assert done.returncode == 0, f"{' '.join(args)}: {done.stderr}"
        return done.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    return Installed(tmp_path_factory.mktemp("package"))


def test_the_wheel_installs_and_runs_from_another_directory(installed, tmp_path):
    sdist, wheel = installed.sdist, installed.wheel
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {path.name for path in (ROOT / "xvoe" / "weights").glob("*.pt")}
    assert {Path(name).name for name in names if name.startswith("xvoe/weights/")} == shipped
    sources = {str(path.relative_to(ROOT)) for path in (ROOT / "xvoe").rglob("*.py")} \
        | {f"xvoe/{path.relative_to(ROOT)}" for path in (ROOT / "inference").rglob("*.py")}
    assert sources <= set(names), f"missing from the wheel: {sorted(sources - set(names))[:5]}"
    assert "xvoe/examples/frame_change.py" in names
    assert {name.split("/")[0] for name in names if ".dist-info/" not in name} == {"xvoe"}
    licence = (ROOT / "LICENSE").read_text()
    assert "MIT License" in licence
    assert [zipfile.ZipFile(wheel).read(n).decode() for n in names if n.endswith(".dist-info/licenses/LICENSE")
            or n.endswith(".dist-info/LICENSE")] == [licence]
    with tarfile.open(sdist) as archive:
        found = archive.getnames()
        assert archive.extractfile(next(n for n in found if n.endswith("/LICENSE"))).read().decode() == licence
    assert any(name.endswith("/xvoe/inference/smc.py") for name in found)

    def run(*args: str) -> str:
        return installed.run(tmp_path, *args)

    assert run("python", "-c", "import xvoe; print(xvoe.__file__)").startswith(str(installed.root / "venv"))
    assert run("python", "-c", "import importlib.util, xvoe.inference.score; print(importlib.util.find_spec("
               "'inference'))").strip() == "None"
    version = run("python", "-c", "import xvoe; print(xvoe.__version__)").strip()
    assert run("xvoe", "--version").strip() == f"xvoe {version}"
    run("xvoe", "generate", "--split", "test", "--pairs", "2", "--workers", "1", "--out", "test.h5", "--quiet")
    run("xvoe", "score", "--model", "random", "--data", "test.h5", "--out", "scores/random.csv", "--quiet")
    run("xvoe", "metrics", "scores/random.csv", "--out", "report", "--rounds", "20")
    assert (tmp_path / "report" / "metrics.csv").read_text().count("\n") > 11


def doc_commands(path: Path) -> list[str]:
    """The `xvoe` command lines of a document's plain code blocks, in order, comments cut."""
    commands, block = [], None      # the open block's language ("" for a plain one), None outside
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            block = line[3:] if block is None else None
            continue
        if block == "" and line.startswith("xvoe "):
            commands.append(line.split("  #")[0].strip())
    return commands


def test_evaluate_your_model_runs_as_written_from_elsewhere(installed, tmp_path):
    """docs/evaluate-your-model.md, every `xvoe` command as written, in a folder outside the
    checkout, against the installed wheel; only the split is smaller (2 pairs a setting) and the
    release's imitation is written by the test's own writer, as the document's `python -c` does."""
    from tests.test_import import write_release

    commands = doc_commands(ROOT / "docs" / "evaluate-your-model.md")
    assert any("xvoe.examples.frame_change:FrameChange" in c for c in commands) and len(commands) >= 10
    write_release(tmp_path / "X-VoE")
    for command in commands:
        args = command.replace("--pairs 100", "--pairs 2").split()
        installed.run(tmp_path, *args)
    for written in ("change.csv", "report/metrics.csv", "report/onset.csv", "pair.mp4", "released.h5",
                    "report-released/metrics.csv", "released-pair.mp4"):
        assert (tmp_path / written).stat().st_size > 0, written
    assert "score" in (tmp_path / "change.csv").read_text().splitlines()[0].split(",")
