"""lcreg as a user installs it: a wheel (``pip install .``), used from a directory outside the repository.

The wheel is built and installed into a folder put first on ``PYTHONPATH`` (the dependencies are this environment's),
so the commands below import the installed copy, not the source tree.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder holding lcreg installed from its wheel (with ``bin/lcreg``)."""
    root = tmp_path_factory.mktemp("install")
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", root / "wheel", REPO], check=True)
    (wheel,) = (root / "wheel").glob("lcreg-*.whl")
    subprocess.run([*pip, "install", "--no-deps", "--target", root / "site", wheel], check=True)
    return root / "site"


def run(installed: Path, cwd: Path, *argv: str | Path) -> subprocess.CompletedProcess[str]:
    """``argv`` in ``cwd`` with the installed lcreg first on the path (``lcreg``: its console script)."""
    head = [sys.executable, str(installed / "bin" / "lcreg")] if argv[0] == "lcreg" else [sys.executable]
    env = {**os.environ, "PYTHONPATH": str(installed), "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"}
    env.pop("LCREG_DEBUG", None)
    args = [*head, *(str(a) for a in argv[1:])] if argv[0] == "lcreg" else [*head, *(str(a) for a in argv)]
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=300, check=False)


def test_the_installed_package_is_the_one_imported(installed: Path, tmp_path: Path) -> None:
    code = "import lcreg, lcreg.config; print(lcreg.__file__); print(lcreg.config.configs_root())"
    done = run(installed, tmp_path, "-c", code)
    assert done.returncode == 0, done.stderr
    module, configs = done.stdout.split()
    assert Path(module).is_relative_to(installed) and Path(configs) == installed / "lcreg" / "configs"


def test_help_and_pretrained_weights_work_from_the_install(installed: Path, tmp_path: Path) -> None:
    done = run(installed, tmp_path, "lcreg", "--help")
    assert done.returncode == 0 and "lcreg register" in done.stdout, done.stderr
    done = run(installed, tmp_path, "-c", "import lcreg; print(type(lcreg.pretrained('dvds-modelnet40')).__name__)")
    assert done.returncode == 0 and done.stdout.split()[-1] == "DVDs", done.stderr


def test_register_two_files_from_the_install(installed: Path, tmp_path: Path) -> None:
    gen = np.random.default_rng(0)
    sphere = gen.normal(size=(800, 3)) * np.array([1.0, 0.6, 0.3])
    for name, cloud in (("a.xyz", sphere), ("b.xyz", sphere @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T)):
        np.savetxt(tmp_path / name, cloud)
    done = run(installed, tmp_path, "lcreg", "register", "a.xyz", "b.xyz", "--method", "icp", "--out", "T.txt")
    assert done.returncode == 0, done.stderr
    assert np.loadtxt(tmp_path / "T.txt").shape == (4, 4)


def test_fit_a_documented_recipe_by_its_repository_path(installed: Path, tmp_path: Path) -> None:
    """``configs/dvds.yaml`` is not a file here: it is read from the package's configs (with what it composes)."""
    steps = ["--trainer.max_steps=1", "--trainer.limit_val_batches=1", "--data.init_args.num_points=64"]
    done = run(installed, tmp_path, "lcreg", "fit", "--config", "configs/dvds.yaml", *steps)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "lcreg: this run logs to" in done.stdout + done.stderr
    assert list((tmp_path / "runs").rglob("last.ckpt"))


def test_a_data_root_missing_here_is_one_line_naming_the_option(installed: Path, tmp_path: Path) -> None:
    done = run(installed, tmp_path, "lcreg", "fit", "--config", "configs/dcp_lc.yaml", "--trainer.max_steps=1")
    assert done.returncode == 1
    error = [line for line in done.stderr.splitlines() if line.startswith("lcreg: error:")]
    assert len(error) == 1 and "--data.init_args.root" in error[0] and str(tmp_path.parent / "shared") in error[0]
    assert "Traceback" not in done.stderr


def test_reproduce_runs_from_the_install(installed: Path, tmp_path: Path) -> None:
    args = ["--budget", "smoke", "--seeds", "0", "--only", "paper/model_A", "--out", "X"]
    done = run(installed, tmp_path, "lcreg", "reproduce", "ablation", *args)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "X" / "ablation.md").is_file() and (tmp_path / "X" / "ablation.jsonl").is_file()
