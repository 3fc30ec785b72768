from __future__ import annotations

import pytest
import torch
from torch import nn

from lcreg.checks import ShapeError, TooFewPointsError
from lcreg.nn import dgcnn
from lcreg.nn.dgcnn import DGCNN, edge_conv, edge_features
from lcreg.nn.mlp import PointwiseMLP

CHANNELS = (6, 8, 10, 12)
EMB = 16
K = 5


def _layer(mlp: PointwiseMLP, x: torch.Tensor, slope: float) -> torch.Tensor:
    """One eval-mode ``Linear -> BatchNorm -> activation`` layer written out as a formula."""
    lin, norm = mlp.linears[0], mlp.norms[0]
    assert isinstance(lin, nn.Linear) and lin.bias is None and isinstance(norm, nn.BatchNorm1d)
    assert norm.running_mean is not None and norm.running_var is not None
    z = x @ lin.weight.T
    z = norm.weight * (z - norm.running_mean) / torch.sqrt(norm.running_var + norm.eps) + norm.bias
    return torch.where(z > 0, z, slope * z)


def _nearest(features: torch.Tensor, i: int, k: int) -> torch.Tensor:
    """Indices of the ``k`` rows of ``features (N, C)`` nearest to row ``i`` (itself included), by an explicit sort."""
    dist = ((features - features[i]) ** 2).sum(-1)
    return torch.argsort(dist)[:k]


def _static_reference(net: DGCNN, points: torch.Tensor) -> torch.Tensor:
    """Per point: edge tensor [x_j, x_i] over its k nearest xyz neighbours, layers applied in sequence to it."""
    out = torch.empty(*points.shape[:2], net.emb_dims, dtype=points.dtype)
    for b, cloud in enumerate(points):
        for i in range(cloud.shape[0]):
            nbr = _nearest(cloud, i, net.k)
            h = torch.cat([cloud[nbr], cloud[i].expand(net.k, 3)], dim=-1)  # (k, 6)
            pooled = []
            for mlp in net.edge_layers:
                assert isinstance(mlp, PointwiseMLP)
                h = _layer(mlp, h, 0.0)
                pooled.append(h.max(dim=0).values)
            assert isinstance(net.head, PointwiseMLP)
            out[b, i] = _layer(net.head, torch.cat(pooled), 0.0)
    return out


def _dynamic_reference(net: DGCNN, points: torch.Tensor, slope: float) -> torch.Tensor:
    """Per layer: a new graph on the current features, edge tensor [f_j, f_i], max over the neighbours."""
    out = torch.empty(*points.shape[:2], net.emb_dims, dtype=points.dtype)
    for b, cloud in enumerate(points):
        f = cloud
        pooled = []
        for mlp in net.edge_layers:
            assert isinstance(mlp, PointwiseMLP)
            rows = []
            for i in range(f.shape[0]):
                nbr = _nearest(f, i, net.k)
                edges = torch.cat([f[nbr], f[i].expand(net.k, -1)], dim=-1)
                rows.append(_layer(mlp, edges, slope).max(dim=0).values)
            f = torch.stack(rows)
            pooled.append(f)
        assert isinstance(net.head, PointwiseMLP)
        out[b] = _layer(net.head, torch.cat(pooled, dim=-1), slope)
    return out


def _net(graph: str, act: str = "relu", seed: int = 0) -> DGCNN:
    """Float64 eval-mode DGCNN with non-trivial BatchNorm affine terms and running statistics."""
    torch.manual_seed(seed)
    net = DGCNN(EMB, K, graph, channels=CHANNELS, act=act).double()  # type: ignore[arg-type]
    with torch.no_grad():
        for module in net.modules():
            if isinstance(module, nn.BatchNorm1d):
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.3, 0.3)
    net.train()
    with torch.no_grad():
        for _ in range(3):
            net(torch.randn(2, 30, 3, dtype=torch.float64) * 1.3 + 0.2)
    return net.eval()


def _points(b: int = 2, n: int = 20, seed: int = 1) -> torch.Tensor:
    return torch.randn(b, n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_edge_features_are_neighbour_then_centre() -> None:
    f = torch.arange(12.0).reshape(1, 4, 3)
    idx = torch.tensor([[[1, 2], [0, 0], [3, 1], [2, 2]]])
    e = edge_features(f, idx)
    assert e.shape == (1, 4, 2, 6)
    torch.testing.assert_close(e[0, 2, 0], torch.cat([f[0, 3], f[0, 2]]))
    torch.testing.assert_close(e[0, 0, 1], torch.cat([f[0, 2], f[0, 0]]))


def test_static_graph_matches_a_per_point_loop() -> None:
    net = _net("static")
    points = _points()
    with torch.no_grad():
        out = net(points)
    assert out.shape == (2, 20, EMB)
    torch.testing.assert_close(out, _static_reference(net, points))


@pytest.mark.parametrize("act,slope", [("relu", 0.0), ("leaky_relu", 0.2)])
def test_dynamic_graph_matches_a_per_point_loop(act: str, slope: float) -> None:
    net = _net("dynamic", act)
    points = _points(n=16)
    with torch.no_grad():
        out = net(points)
    torch.testing.assert_close(out, _dynamic_reference(net, points, slope))


@pytest.mark.parametrize("graph", ["static", "dynamic"])
def test_without_batch_norm_every_layer_is_linear_with_a_bias_then_the_activation(graph: str) -> None:
    net = DGCNN(EMB, K, graph, channels=CHANNELS, batch_norm=False).double()  # type: ignore[arg-type]
    mlps = [*net.edge_layers, net.head]
    assert not any(isinstance(m, nn.BatchNorm1d) for m in net.modules())
    assert all(m.linears[0].bias is not None for m in mlps)  # type: ignore[union-attr,index]
    points = _points(n=16)
    with torch.no_grad():
        torch.testing.assert_close(net.train()(points), net.eval()(points))  # the same function in both modes


def test_static_and_dynamic_layer_widths() -> None:
    static, dynamic = DGCNN(EMB, K, "static", channels=CHANNELS), DGCNN(EMB, K, "dynamic", channels=CHANNELS)
    widths_s = [m.linears[0].in_features for m in static.edge_layers]  # type: ignore[index,union-attr]
    widths_d = [m.linears[0].in_features for m in dynamic.edge_layers]  # type: ignore[index,union-attr]
    assert widths_s == [6, 6, 8, 10]  # the same edge tensor goes through the layers in sequence
    assert widths_d == [6, 12, 16, 20]  # new [f_j, f_i] edges of the previous output
    assert static.head.linears[0].in_features == sum(CHANNELS)  # type: ignore[union-attr]


@pytest.mark.parametrize("graph", ["static", "dynamic"])
def test_point_permutation_equivariance(graph: str) -> None:
    net = _net(graph)
    points = _points(n=24)
    perm = torch.randperm(24, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        torch.testing.assert_close(net(points[:, perm]), net(points)[:, perm])


def test_static_embedding_depends_on_coordinates_not_only_on_the_graph() -> None:
    """The edge features are raw coordinates: a rotation keeps the graph but changes the embedding (not invariant)."""
    net = _net("static")
    points = _points()
    rot = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64))[0]
    with torch.no_grad():
        assert not torch.allclose(net(points @ rot.T), net(points), atol=1e-3)


def test_gradients_reach_the_coordinates_and_every_parameter() -> None:
    torch.manual_seed(0)
    net = DGCNN(EMB, K, "static", channels=CHANNELS).double().train()
    points = _points().requires_grad_(True)
    (net(points) * torch.randn(2, 20, EMB, dtype=torch.float64)).sum().backward()
    assert points.grad is not None and torch.isfinite(points.grad).all() and points.grad.abs().sum() > 0
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="graph"):
        DGCNN(graph="knn")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="k"):
        DGCNN(k=0)
    with pytest.raises(TooFewPointsError, match="k=5"):
        DGCNN(EMB, K, channels=CHANNELS)(torch.randn(1, 4, 3))


@pytest.mark.parametrize("batch_norm", [True, False])
def test_edge_conv_equals_the_layer_on_explicit_edge_features(batch_norm: bool) -> None:
    torch.manual_seed(0)
    layer = PointwiseMLP([2 * 5, 7, 4], batch_norm=batch_norm, act="leaky_relu").double().train()
    features = torch.randn(2, 30, 5, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 30, (2, 30, 6))
    direct = layer(edge_features(features, idx))
    fast = edge_conv(layer, features, idx)
    torch.testing.assert_close(fast, direct, atol=1e-12, rtol=0)
    (g_direct,) = torch.autograd.grad(direct.square().sum(), features)
    (g_fast,) = torch.autograd.grad(fast.square().sum(), features)
    torch.testing.assert_close(g_fast, g_direct, atol=1e-10, rtol=0)


def test_edge_conv_rejects_a_foreign_layer_or_a_width_mismatch() -> None:
    features, idx = torch.randn(1, 10, 5), torch.randint(0, 10, (1, 10, 3))
    with pytest.raises(TypeError, match="PointwiseMLP"):
        edge_conv(nn.Linear(10, 4), features, idx)
    with pytest.raises(ShapeError, match="features"):
        edge_conv(PointwiseMLP([8, 4]), features, idx)  # expects 4 input channels, gets 5


@pytest.mark.parametrize("graph", ["static", "dynamic"])
def test_pooling_with_neighbour_max_gives_amaxs_embedding_and_weight_gradients(
    graph: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    torch.manual_seed(0)
    net = DGCNN(EMB, K, graph, channels=CHANNELS).train()  # type: ignore[arg-type]
    points = _points().float()

    def embedding_and_gradients() -> list[torch.Tensor]:
        net.zero_grad()
        out = net(points)
        out.sum().backward()
        return [out.detach(), *(p.grad.clone() for p in net.parameters() if p.grad is not None)]

    ours = embedding_and_gradients()
    monkeypatch.setattr(dgcnn, "neighbour_max", lambda values: values.amax(dim=2))  # the previous pooling
    previous = embedding_and_gradients()
    assert len(ours) == len(previous) == 1 + len(list(net.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(ours, previous, strict=True))
