"""KISS-Matcher behind the classical interface (optional dependency): it registers, and without it one line says so."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import lcreg
from _register_pairs import errors, make_pair  # type: ignore[import-not-found]
from lcreg.baselines.kiss import KISSMatcher
from lcreg.checks import MissingDependencyError
from lcreg.registration.voxel import auto_voxel_size


@pytest.fixture
def without_kiss(monkeypatch: pytest.MonkeyPatch) -> None:
    """As on Windows or Linux arm64, where kiss-matcher has no wheel: importing it fails."""
    monkeypatch.setitem(sys.modules, "kiss_matcher", None)


@pytest.mark.parametrize("method", ["kiss", "kiss+icp"])
def test_register_recovers_a_large_motion(method: str) -> None:
    pytest.importorskip("kiss_matcher")
    src, ref, gt = make_pair()
    result = lcreg.register(src, ref, method)
    rre, rte = errors(result.transform, gt)
    limit = (1.0, 0.01) if method.endswith("+icp") else (10.0, 0.1)  # a coarse step: within ICP's reach
    assert rre < limit[0] and rte < limit[1], (rre, rte)
    assert result.fitness > 0.9 and result.method == method


def test_the_module_registers_batches_like_the_other_classical_methods() -> None:
    pytest.importorskip("kiss_matcher")
    src, ref, gt = make_pair()
    model = KISSMatcher(voxel_size=auto_voxel_size(src, ref))
    out = model.register(torch.from_numpy(src)[None], torch.from_numpy(ref)[None])
    rre, rte = errors(out.transform_ref_src[0].numpy(), gt)
    assert rre < 10.0 and rte < 0.1 and out.transform_ref_src.dtype == torch.float64
    assert float(out.aux["fitness"][0]) > 0.9 and bool(out.converged[0])


def test_without_the_package_the_method_says_how_to_get_it(without_kiss: None) -> None:
    src, ref, _ = make_pair()
    model = KISSMatcher()  # building and listing need nothing
    with pytest.raises(MissingDependencyError, match=r"pip install 'lcreg\[kiss\]'") as info:
        lcreg.register(src, ref, "kiss")
    assert isinstance(info.value, ImportError) and "\n" not in str(info.value)
    with pytest.raises(MissingDependencyError, match="Linux x86_64 and macOS arm64"):
        model.register(torch.from_numpy(src)[None], torch.from_numpy(ref)[None])


def test_the_command_line_error_is_one_line(tmp_path: Path) -> None:
    src, ref, _ = make_pair()
    np.save(tmp_path / "a.npy", src)
    np.save(tmp_path / "b.npy", ref)
    script = (
        "import sys; sys.modules['kiss_matcher'] = None; from lcreg.__main__ import main; "
        "sys.argv = ['lcreg', 'register', 'a.npy', 'b.npy', '--method', 'kiss']; main()"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert "kiss-matcher" in lines[0] and "pip install 'lcreg[kiss]'" in lines[0] and "Traceback" not in done.stderr


def test_invalid_settings_are_named() -> None:
    with pytest.raises(ValueError, match="robin_noise_bound_gain"):
        KISSMatcher(robin_noise_bound_gain=0.0)
    with pytest.raises(ValueError, match="num_max_corr"):
        KISSMatcher(num_max_corr=2)


def test_no_solution_warns_or_runs_the_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("kiss_matcher")
    src, ref, gt = make_pair()
    monkeypatch.setattr(KISSMatcher, "estimate_pair", lambda self, a, b: (np.eye(4), False))  # too few inliers
    with pytest.warns(lcreg.registration.LowFitnessWarning, match="kiss found no solution"):
        alone = lcreg.register(src, ref, "kiss+icp")
    assert alone.extra["coarse_valid"] is False
    rescued = lcreg.register(src, ref, "kiss+icp", fallback="ransac+icp")
    assert rescued.method == "ransac+icp" and rescued.extra["fallback"]["no_solution"] is True
    assert errors(rescued.transform, gt)[0] < 1.0
