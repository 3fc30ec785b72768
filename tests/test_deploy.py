"""lcreg.deploy: an IC-LK model as a fixed-iteration graph, equal to the eager solve; TorchScript and ONNX files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lcreg.deploy import DeployedLK, _cholesky_solve, export_registrar
from lcreg.geometry import se3

from _weights_files import tiny_model  # type: ignore[import-not-found]


def _pairs(b: int = 3, n: int = 200) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    src = torch.rand(b, n, 3, generator=g) - 0.5
    twist = torch.tensor([0.15, -0.1, 0.2, 0.05, 0.08, -0.04]) * torch.linspace(0.5, 1.5, b)[:, None]
    return src, se3.transform_points(se3.exp(twist), src)


def _eager(model: torch.nn.Module, src: torch.Tensor, ref: torch.Tensor, iterations: int) -> torch.Tensor:
    model.solver.tolerance = 0.0  # every item runs all iterations, as the graph does
    with torch.no_grad():
        return model.solver(model.encoder.eval(), src, ref, max_iterations=iterations).transform_ref_src


@pytest.mark.parametrize(("kind", "jacobian"), [("dvds", "analytic"), ("pointnetlk", "finite_difference")])
def test_the_graph_equals_the_eager_solve(kind: str, jacobian: str) -> None:
    model = tiny_model(kind, seed=1, jacobian=jacobian).eval()
    src, ref = _pairs()
    graph = DeployedLK(model, iterations=5).eval()
    with torch.no_grad():
        out = graph(src, ref)
    torch.testing.assert_close(out, _eager(model, src, ref, 5), atol=1e-5, rtol=0)


def test_the_graph_keeps_the_models_starts(tmp_path: Path) -> None:
    """With ``eval_start_angles_deg`` the graph picks, per item, the start the eager solve picks (a 126° turn about
    z, where starts other than the identity win), in the module and in its TorchScript file."""
    model = tiny_model("dvds", seed=1).eval()
    model.eval_start_angles_deg, model.eval_iterations = (60.0, 120.0), 5
    src, ref = _pairs()
    ref = ref @ se3.exp(torch.tensor([[0.0, 0.0, 2.2, 0.0, 0.0, 0.0]]))[0, :3, :3].T
    ref = ref + 0.02 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(0))  # no start fits exactly
    model.solver.tolerance = 0.0
    with torch.no_grad():
        eager = model(src, ref)
        graph = DeployedLK(model).eval()
        out = graph(src, ref)
    assert graph.num_starts == 13 and (eager.aux["start"] != 0).any()
    torch.testing.assert_close(out, eager.transform_ref_src, atol=1e-5, rtol=0)
    path = export_registrar(model, tmp_path / "dvds.ts", "torchscript", points=200)
    torch.testing.assert_close(torch.jit.load(str(path))(src, ref), out, atol=1e-6, rtol=0)
    model.eval_start_margin = 0.999  # the margin travels: no start beats the identity by that much
    with torch.no_grad():
        eager, graph = model(src, ref), DeployedLK(model).eval()
        assert graph.start_margin == 0.999 and (eager.aux["start"] == 0).all()
        torch.testing.assert_close(graph(src, ref), eager.transform_ref_src, atol=1e-5, rtol=0)
        assert (graph(src, ref) - out).abs().max() > 0.1  # not the margin-0 answer


def test_cholesky_solve_matches_torch_solve() -> None:
    g = torch.Generator().manual_seed(2)
    m = torch.randn(4, 6, 6, generator=g, dtype=torch.float64)
    a, rhs = m @ m.transpose(1, 2) + 0.1 * torch.eye(6, dtype=torch.float64), torch.randn(4, 6, 9, dtype=torch.float64)
    torch.testing.assert_close(_cholesky_solve(a, rhs), torch.linalg.solve(a, rhs), atol=1e-9, rtol=1e-9)


def test_torchscript_file_runs_alone_and_agrees(tmp_path: Path) -> None:
    model = tiny_model("dvds", seed=3).eval()
    path = export_registrar(model, tmp_path / "dvds.ts", "torchscript", points=200, iterations=4)
    src, ref = _pairs(b=2, n=150)  # other batch and size than the example
    with torch.no_grad():
        expected = DeployedLK(model, iterations=4)(src, ref)
    torch.testing.assert_close(torch.jit.load(str(path))(src, ref), expected, atol=1e-6, rtol=0)


@pytest.mark.parametrize("angles", [(), (60.0,)], ids=["identity", "starts"])
def test_onnx_file_runs_in_onnxruntime_and_agrees(tmp_path: Path, angles: tuple[float, ...]) -> None:
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    model = tiny_model("dvds", seed=4).eval()
    model.eval_start_angles_deg = angles
    path = export_registrar(model, tmp_path / "dvds.onnx", "onnx", points=200, iterations=4)
    src, ref = _pairs(b=2, n=150)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = session.run(None, {"points_src": src.numpy(), "points_ref": ref.numpy()})[0]
    with torch.no_grad():
        expected = DeployedLK(model, iterations=4)(src, ref).numpy()
    np.testing.assert_allclose(out, expected, atol=1e-5)


def test_other_models_and_settings_are_refused() -> None:
    from lcreg.baselines.classical import ICP

    with pytest.raises(TypeError, match="IC-LK model"):
        DeployedLK(ICP())
    with pytest.raises(ValueError, match="autodiff"):
        DeployedLK(tiny_model("dvds", jacobian="autodiff"))
    with pytest.raises(ValueError, match="export format"):
        export_registrar(tiny_model("dvds"), "x.bin", "tflite")  # type: ignore[arg-type]


def test_the_command_writes_a_file_from_shipped_weights(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lcreg.cli import main

    out = tmp_path / "dvds.ts"
    main(["export", "dvds-modelnet40", "--format", "torchscript", "--out", str(out), "--points", "128"])
    assert f"wrote {out}" in capsys.readouterr().out
    src, ref = _pairs(b=1, n=128)
    assert torch.jit.load(str(out))(src, ref).shape == (1, 4, 4)
    with pytest.raises(SystemExit) as info:
        main(["export", "no-such-weights", "--format", "torchscript", "--out", str(out)])
    assert info.value.code == 1 and "no-such-weights" in capsys.readouterr().err


def test_onnx_without_its_packages_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import sys

    from lcreg.deploy import main

    monkeypatch.setitem(sys.modules, "onnxscript", None)
    with pytest.raises(SystemExit) as info:
        main(["dvds-modelnet40", "--format", "onnx", "--out", "x.onnx"])
    err = capsys.readouterr().err
    assert info.value.code == 1 and "pip install 'lcreg[export]'" in err and len(err.strip().splitlines()) == 1
