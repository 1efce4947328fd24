"""Builds the wheel, installs it (not editable) in a fresh venv, and checks it from outside.

Usage: python scripts/check_wheel.py [--keep]

Run it with the Python of an environment that already has taptr's dependencies (CI's
venv): the fresh venv sees that environment's packages through a ``.pth`` file, so torch is
not downloaded again, and the wheel is installed with ``--no-deps`` and then checked with
``pip check``. The editable taptr of that environment stays invisible (``.pth`` files of an
added directory are not processed), and every check asserts that ``taptr`` is imported
from the fresh venv.

Checks: the wheel holds every module of ``src/taptr`` and ``py.typed`` (and the bundled
weights when the source tree has them, byte for byte), and nothing else at the top level;
``import taptr`` works from a folder outside the source tree; the bundled weights resolve
(when present); the ``taptr`` console script runs ``--version``, ``sample-video`` and a
tiny ``track``. Exit status 0 when everything passes.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import sysconfig
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = Path("taptr") / "weights" / "taptr-small-synthetic.pth"

INSIDE = """
import hashlib, json, sys
from pathlib import Path
import taptr, taptr.weights.registry
package = Path(taptr.__file__).parent
assert Path(sys.prefix) in package.parents, f"taptr imported from {package}, not the venv"
weights = taptr.weights.registry.bundled_path("taptr-small-synthetic")
print(json.dumps({
    "version": taptr.__version__,
    "package": str(package),
    "py_typed": (package / "py.typed").is_file(),
    "weights": None if weights is None else hashlib.sha256(weights.read_bytes()).hexdigest(),
}))
if weights is not None:
    predictor = taptr.Predictor.from_pretrained()
    print("bundled model input size", predictor.input_size)
"""


def run(command: list[str], cwd: Path, **kwargs: object) -> str:
    """Runs a command, echoing it; fails loudly with its output."""
    shown = " ".join(str(c) if len(str(c)) < 100 else "<script>" for c in command)
    print("+", shown, flush=True)
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, **kwargs)
    if done.returncode != 0:
        sys.exit(f"failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return done.stdout


def copy_sources(target: Path) -> None:
    """The tracked and untracked-but-not-ignored files, so stale build/ output cannot leak in."""
    listing = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout
    for name in filter(None, listing.decode().split("\0")):
        source = REPO / name
        if source.is_file():  # a deleted tracked file is still listed
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            (target / name).write_bytes(source.read_bytes())


def build_wheel(sources: Path, dist: Path) -> Path:
    """``pip wheel`` without build isolation when setuptools is importable (no download)."""
    try:
        import setuptools  # noqa: F401

        isolation = ["--no-build-isolation"]
    except ImportError:
        isolation = []
    pip = [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", *isolation]
    run([*pip, "--wheel-dir", str(dist), str(sources)], cwd=sources)
    (wheel,) = dist.glob("taptr-*.whl")
    return wheel


def check_contents(wheel: Path) -> None:
    """Every module of the source package, py.typed, the weights if present, nothing else."""
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        source = REPO / "src"
        modules = {str(p.relative_to(source)) for p in (source / "taptr").rglob("*.py")}
        missing = sorted(m for m in modules if m not in names)
        assert not missing, f"modules missing from the wheel: {missing}"
        assert "taptr/py.typed" in names, "py.typed missing from the wheel"
        top = {n.split("/", 1)[0] for n in names}
        assert {t for t in top if not t.endswith(".dist-info")} == {"taptr"}, top
        weights = source / WEIGHTS
        if weights.is_file():
            assert str(WEIGHTS) in names, f"{WEIGHTS} exists but is not in the wheel"
            assert archive.read(str(WEIGHTS)) == weights.read_bytes()
    print(f"wheel contents ok: {len(names)} files, {len(modules)} modules")


def make_venv(target: Path) -> Path:
    """A fresh venv whose imports fall back to this environment's packages."""
    # without pip (and the setuptools it brings), which would shadow this environment's
    run([sys.executable, "-m", "venv", "--without-pip", str(target)], cwd=target.parent)
    python = target / "bin" / "python"
    site = run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=target
    )
    parents = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))
    Path(site.strip(), "_taptr_ci_parent.pth").write_text("\n".join(parents) + "\n")
    return python


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = parser.parse_args()
    start = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="taptr-wheel-"))
    try:
        (work / "src").mkdir()
        copy_sources(work / "src")
        wheel = build_wheel(work / "src", work / "dist")
        check_contents(wheel)
        python = make_venv(work / "venv")
        pip = [sys.executable, "-m", "pip", "--python", str(python)]  # this pip, run for the venv
        run([*pip, "install", "--quiet", "--no-deps", str(wheel)], cwd=work)
        run([*pip, "check"], cwd=work)
        outside = work / "elsewhere"
        outside.mkdir()
        env = {**os.environ, "PYTHONPATH": "", "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
        report = run([str(python), "-I", "-c", INSIDE], cwd=outside, env=env)
        print(report.strip())
        assert '"py_typed": true' in report, "py.typed not installed"
        weights = REPO / "src" / WEIGHTS
        if weights.is_file():
            digest = hashlib.sha256(weights.read_bytes()).hexdigest()
            assert f'"weights": "{digest}"' in report, "installed weights differ from the source"
        else:
            assert '"weights": null' in report
            print(f"note: {WEIGHTS} is not in the source tree; its check was skipped")
        taptr = str(work / "venv" / "bin" / "taptr")
        assert run([taptr, "--version"], cwd=outside, env=env).strip().startswith("taptr ")
        run([taptr, "sample-video", "sample.mp4"], cwd=outside, env=env)
        track = [taptr, "track", "sample.mp4", "--grid", "2", "--checkpoint", "tiny"]
        run([*track, "--max-frames", "8", "--device", "cpu", "--out", "out"], cwd=outside, env=env)
        for name in ("tracks.npz", "tracks.csv", "overlay.mp4"):
            assert (outside / "out" / name).is_file(), f"taptr track wrote no {name}"
    finally:
        if args.keep:
            print(f"kept {work}")
        else:
            subprocess.run(["rm", "-rf", str(work)], check=False)
    print(f"wheel check passed in {time.perf_counter() - start:.0f} s: {wheel.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
