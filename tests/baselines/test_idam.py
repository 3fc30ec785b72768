from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml

from lcreg.baselines.idam import (
    IDAM,
    SIMILARITY_CLAMP,
    GNNEncoder,
    edge_differences,
    hybrid_weights,
    negative_entropy,
    procrustes_step,
    sample_training_subsets,
    similarity_input,
)
from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.types import RegistrationBatch, RegistrationResult

from _host_contract import (  # type: ignore[import-not-found]
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_rotation_equivariance,
    check_training_lowers_loss,
    lc_terms,
    tiny_batch,
)

EMB = 16
TINY = {"emb_dims": EMB, "k": 8, "gnn_channels": (16, 16), "hidden": 16}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _model(seed: int = 0, **overrides: object) -> IDAM:
    torch.manual_seed(seed)
    return IDAM(**{**TINY, **overrides})  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    return tiny_batch(batch_size=3, num_points=72, independent_sampling=False)


# --- host contract -----------------------------------------------------------------------------------------------
def test_forward_backward(batch: RegistrationBatch) -> None:
    result = check_forward_backward(_model, batch)
    assert (result.num_iters == 3).all() and result.converged.all()
    assert not result.transform_ref_src.requires_grad  # R, t detached as in the original
    n = 72 // 6
    assert result.aux["similarity"].shape == (3, 3, n, n) and result.aux["weight_logits"].shape == (3, 3, n)
    assert result.aux["similarity"].abs().max() <= SIMILARITY_CLAMP


def test_training_lowers_loss(batch: RegistrationBatch) -> None:
    check_training_lowers_loss(_model, batch, steps=12)


def test_local_consistency_reaches_the_gnn_encoder(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(lambda terms: _model(loss_terms=terms), batch)


def test_bad_inputs_raise_typed_errors() -> None:
    check_bad_inputs(_model)
    with pytest.raises(ValueError, match=f"built for {EMB + 1} features, the encoder has {EMB}"):
        IDAM(**TINY, loss_terms=lc_terms(feature_dim=EMB + 1))  # type: ignore[arg-type]
    for bad in ({"num_iters": 0}, {"num_kept": 0}, {"positive_threshold": 0.0}):
        with pytest.raises(ValueError):
            _model(**bad)


def test_training_forward_needs_the_ground_truth(batch: RegistrationBatch) -> None:
    with pytest.raises(ValueError, match="transform_ref_src"):
        _model().training_forward(RegistrationBatch(batch.points_src, batch.points_ref))


# --- feature extractor -------------------------------------------------------------------------------------------
def test_edge_differences_match_a_loop() -> None:
    feats = torch.randn(2, 10, 5, dtype=torch.float64)
    idx = torch.randint(0, 10, (2, 10, 4))
    out = edge_differences(feats, idx)
    for b in range(2):
        for i in range(10):
            for j in range(4):
                torch.testing.assert_close(out[b, i, j], feats[b, idx[b, i, j]] - feats[b, i])


def test_gnn_encoder_is_translation_invariant_and_uses_the_graph() -> None:
    torch.manual_seed(0)
    enc = GNNEncoder(emb_dims=EMB, k=8, channels=(16,)).double().eval()
    assert len(enc.layers) == 2 and enc(torch.randn(1, 20, 3, dtype=torch.float64)).shape == (1, 20, EMB)
    points = torch.randn(2, 40, 3, dtype=torch.float64)
    torch.testing.assert_close(enc(points + torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)), enc(points))
    with pytest.raises(ValueError, match="k=8"):
        enc(points[:, :7])


# --- similarity convolution --------------------------------------------------------------------------------------
def test_similarity_input_matches_an_explicit_pair_loop() -> None:
    gen = torch.Generator().manual_seed(1)
    f = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64)
    g = torch.randn(2, 4, 3, generator=gen, dtype=torch.float64)
    x = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64)
    y = torch.randn(2, 4, 3, generator=gen, dtype=torch.float64)
    y[0, 1] = x[0, 2]  # a coincident pair: distance 0, direction 0
    out = similarity_input(f, g, x, y)
    assert out.shape == (2, 5, 4, 2 * 3 + 4)
    for b in range(2):
        for i in range(5):
            for j in range(4):
                d = x[b, i] - y[b, j]
                dist = math.sqrt(float((d * d).sum()))
                expected = torch.cat([f[b, i], g[b, j], d.new_tensor([dist]), d / (dist + 1e-8)])
                torch.testing.assert_close(out[b, i, j], expected)
    assert out[0, 2, 1, -4:].abs().max() == 0


def test_hybrid_weights_match_a_hand_computation() -> None:
    logits = torch.tensor([[0.5, -1.0, 2.0, 0.0], [3.0, 1.0, -2.0, 0.0]], dtype=torch.float64)
    s = torch.sigmoid(logits)
    # Even count: torch's (lower) median is the 2nd smallest; entries below it are zeroed.
    keep = torch.tensor([[1.0, 0.0, 1.0, 1.0], [1.0, 1.0, 0.0, 1.0]], dtype=torch.float64)
    expected = s * keep / (s * keep).sum(dim=1, keepdim=True)
    torch.testing.assert_close(hybrid_weights(logits), expected)
    odd = hybrid_weights(torch.tensor([[-1.0, 2.0, 0.0]], dtype=torch.float64))
    e = torch.sigmoid(torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64)) * torch.tensor([0.0, 1.0, 1.0])
    torch.testing.assert_close(odd[0], e / e.sum())


def test_procrustes_step_is_rotation_equivariant_for_fixed_matches_and_weights() -> None:
    gen = torch.Generator().manual_seed(2)
    src = torch.randn(3, 12, 3, generator=gen, dtype=torch.float64)
    ref = torch.randn(3, 10, 3, generator=gen, dtype=torch.float64)
    similarity = torch.randn(3, 12, 10, generator=gen, dtype=torch.float64)
    weights = hybrid_weights(torch.randn(3, 12, generator=gen, dtype=torch.float64))
    # (atol: the contract's random rotation is drawn in float32)
    check_rotation_equivariance(lambda s, r: procrustes_step(s, r, similarity, weights), src, ref, atol=1e-6)


def test_procrustes_step_recovers_a_transform_from_correct_matches() -> None:
    gen = torch.Generator().manual_seed(3)
    transform, _ = random_euler_transform(2, generator=gen, dtype=torch.float64)
    src = torch.randn(2, 9, 3, generator=gen, dtype=torch.float64)
    perm = torch.randperm(9, generator=gen)
    ref = se3.transform_points(transform, src)[:, perm]
    similarity = torch.full((2, 9, 9), -5.0, dtype=torch.float64)
    similarity[:, perm, torch.arange(9)] = 5.0  # src[perm[j]] <-> ref[j]
    weights = torch.rand(2, 9, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(procrustes_step(src, ref, similarity, weights), transform)


def test_selection_and_first_similarity_are_invariant_to_a_common_translation(batch: RegistrationBatch) -> None:
    # The GNN sees coordinate differences only and the pair tensor sees x_i - y_j, so moving both clouds together
    # changes neither the kept points nor the first similarity/weights. (The later iterations are equivariant too
    # when the weighted correspondences are non-degenerate; an untrained network often matches every point to one
    # reference point, where the Procrustes rotation is not unique, so they are not compared here.)
    model = _model().double()
    with torch.no_grad():  # non-trivial BatchNorm running statistics
        model(batch.points_src.double() * 0.8, batch.points_ref.double() + 0.1)
    model.eval()
    src, ref = batch.points_src.double(), batch.points_ref.double()
    shift = torch.tensor([0.4, -0.7, 1.3], dtype=torch.float64)
    base, moved = model(src, ref), model(src + shift, ref + shift)
    for key in ("index_src", "index_ref"):
        assert torch.equal(moved.aux[key], base.aux[key])
    for key in ("scores_src", "scores_ref"):
        torch.testing.assert_close(moved.aux[key], base.aux[key], atol=1e-12, rtol=0)
    for key in ("similarity", "weight_logits"):
        torch.testing.assert_close(moved.aux[key][:, 0], base.aux[key][:, 0], atol=1e-12, rtol=0)


def test_iterations_compose_their_steps_and_use_separate_weights(batch: RegistrationBatch) -> None:
    model = _model(num_iters=2).eval()
    assert len(model.blocks) == 2 and model.blocks[0].trunk is not model.blocks[1].trunk
    src, ref = batch.points_src, batch.points_ref
    result = model(src, ref)
    idx_s, idx_r = result.aux["index_src"], result.aux["index_ref"]
    sub_s = torch.stack([s[i] for s, i in zip(src, idx_s)])
    sub_r = torch.stack([r[i] for r, i in zip(ref, idx_r)])
    f_s = torch.stack([f[i] for f, i in zip(model.encoder(src), idx_s)])
    f_r = torch.stack([f[i] for f, i in zip(model.encoder(ref), idx_r)])
    transform = se3.identity(3)
    for t, block in enumerate(model.blocks):
        moved = se3.transform_points(transform, sub_s)
        sim, logits = block(similarity_input(f_s, f_r, moved, sub_r))
        torch.testing.assert_close(sim, result.aux["similarity"][:, t])
        transform = se3.compose(procrustes_step(moved, sub_r, sim, hybrid_weights(logits)), transform)
    torch.testing.assert_close(result.transform_ref_src, transform)


# --- hard point elimination --------------------------------------------------------------------------------------
def test_evaluation_keeps_the_top_scored_points_of_each_cloud(batch: RegistrationBatch) -> None:
    model = _model().eval()
    result = model(batch.points_src, batch.points_ref[:, :60])
    n = 72 // 6
    scores_src = model.score_head(model.encoder(batch.points_src)).squeeze(-1)
    scores_ref = model.score_head(model.encoder(batch.points_ref[:, :60])).squeeze(-1)
    for b in range(3):
        assert set(result.aux["index_src"][b].tolist()) == set(scores_src[b].topk(n).indices.tolist())
        assert set(result.aux["index_ref"][b].tolist()) == set(scores_ref[b].topk(n).indices.tolist())
    assert model.kept(1024, 1024) == 170 and _model(num_kept=50).kept(96, 40) == 40


def _partial_pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """60 source points; the first 25 have an exact GT counterpart in a shuffled reference, the others none."""
    gen = torch.Generator().manual_seed(seed)
    src = torch.rand(2, 60, 3, generator=gen)
    src[:, 25:] += 3.0  # far from the positives
    transform, _ = random_euler_transform(2, generator=gen)
    image = src.clone()
    image[:, 25:] += 5.0  # the counterparts of the negatives are far from everything
    ref = se3.transform_points(transform, image)
    perm = torch.randperm(60, generator=gen)
    return src, ref[:, perm], transform, perm


def test_training_sampling_picks_ground_truth_pairs() -> None:
    src, ref, transform, _ = _partial_pair()
    torch.manual_seed(0)
    subsets = sample_training_subsets(src, ref, transform, num=12, threshold=0.05)
    assert subsets.index_src.shape == subsets.index_ref.shape == subsets.positive.shape == (2, 12)
    # Half from the positives (source index < 25), half from the negatives; no point twice.
    assert (subsets.index_src[:, :6] < 25).all() and (subsets.index_src[:, 6:] >= 25).all()
    assert subsets.positive[:, :6].all() and not subsets.positive[:, 6:].any()
    assert all(len(set(row.tolist())) == 12 for row in subsets.index_src)
    for b in range(2):
        moved = se3.transform_points(transform[b : b + 1], src[b : b + 1, subsets.index_src[b]])[0]
        chosen = ref[b, subsets.index_ref[b]]
        torch.testing.assert_close(chosen[:6], moved[:6], atol=1e-5, rtol=0)  # the subsets correspond
        nearest = torch.cdist(moved, ref[b]).argmin(dim=1)
        assert torch.equal(subsets.index_ref[b], nearest)  # the reference subset is the GT nearest neighbours


def test_training_sampling_fills_a_missing_group_and_uses_torch_rng() -> None:
    src, ref, transform, _ = _partial_pair(1)
    torch.manual_seed(0)
    first = sample_training_subsets(src, ref, transform, num=60, threshold=0.05)  # only 25 positives
    assert (first.positive.sum(1) == 25).all() and first.positive[:, :25].all()
    assert all(sorted(row.tolist()) == list(range(60)) for row in first.index_src)
    with pytest.raises(ValueError, match="num"):
        sample_training_subsets(src, ref, transform, num=61)
    torch.manual_seed(5)
    a = sample_training_subsets(src, ref, transform, num=10, threshold=0.05).index_src
    torch.manual_seed(5)
    b = sample_training_subsets(src, ref, transform, num=10, threshold=0.05).index_src
    c = sample_training_subsets(src, ref, transform, num=10, threshold=0.05).index_src
    assert torch.equal(a, b) and not torch.equal(a, c)
    # Uniform within the positives: over many draws every positive point gets picked.
    counts = torch.zeros(25)
    for _ in range(60):
        picked = sample_training_subsets(src[:1], ref[:1], transform[:1], num=10, threshold=0.05).index_src[0, :5]
        counts += torch.bincount(picked, minlength=60)[:25].float()
    assert (counts > 0).all()


def test_training_forward_supervises_the_diagonal(batch: RegistrationBatch) -> None:
    result = _model().training_forward(batch)
    n = 72 // 6
    assert torch.equal(result.aux["match_index"], torch.arange(n).expand(3, n))
    assert result.aux["positive"].all()  # same points in both clouds: every point has its exact counterpart
    gt = batch.transform_ref_src
    assert gt is not None
    for b in range(3):
        moved = se3.transform_points(gt[b : b + 1], batch.points_src[b : b + 1, result.aux["index_src"][b]])[0]
        torch.testing.assert_close(batch.points_ref[b, result.aux["index_ref"][b]], moved, atol=1e-5, rtol=0)


# --- losses ------------------------------------------------------------------------------------------------------
def test_negative_entropy_target() -> None:
    sim = torch.randn(2, 5, 4, dtype=torch.float64)
    p = sim.softmax(-1)
    torch.testing.assert_close(negative_entropy(sim, -1), (p * p.log()).sum(-1))
    q = sim.softmax(-2)
    torch.testing.assert_close(negative_entropy(sim, -2), (q * q.log()).sum(-2))
    flat = negative_entropy(torch.zeros(1, 3, 7, dtype=torch.float64), -1)
    torch.testing.assert_close(flat, torch.full((1, 3), -math.log(7), dtype=torch.float64))


def _crafted_result(seed: int = 0) -> RegistrationResult:
    gen = torch.Generator().manual_seed(seed)
    b, t, n = 2, 3, 5
    similarity = torch.randn(b, t, n, n, generator=gen, dtype=torch.float64) * 3
    similarity[0, 1, 2, 2] = 50.0  # correct argmax somewhere
    aux = {
        "similarity": similarity.requires_grad_(),
        "weight_logits": torch.randn(b, t, n, generator=gen, dtype=torch.float64).requires_grad_(),
        "scores_src": torch.randn(b, n, generator=gen, dtype=torch.float64).requires_grad_(),
        "scores_ref": torch.randn(b, n, generator=gen, dtype=torch.float64).requires_grad_(),
        "match_index": torch.arange(n).expand(b, n),
        "positive": torch.tensor([[True, False, True, True, False], [False, True, True, True, True]]),
    }
    return RegistrationResult(
        se3.identity(b, dtype=torch.float64), torch.ones(b, dtype=torch.bool), torch.ones(b, dtype=torch.int64), aux=aux
    )


def test_losses_match_explicit_per_item_loops() -> None:
    result = _crafted_result()
    aux = result.aux
    losses = _model().training_losses(result, RegistrationBatch(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3)))
    sim, logits, positive = aux["similarity"].detach(), aux["weight_logits"].detach(), aux["positive"]
    score = torch.tensor(0.0, dtype=torch.float64)
    for scores, dim in ((aux["scores_src"], -1), (aux["scores_ref"], -2)):
        p = sim[:, 0].softmax(dim)
        score += ((scores.detach() - (p * p.log()).sum(dim)) ** 2).mean()
    match, weight = 0.0, 0.0
    for t in range(3):
        nll, count, bce = 0.0, 0, 0.0
        for b in range(2):
            for i in range(5):
                row = sim[b, t, i]
                if positive[b, i]:
                    nll += float(torch.logsumexp(row, 0) - row[i])
                    count += 1
                label = float(int(row.argmax()) == i)
                s = float(torch.sigmoid(logits[b, t, i]))
                bce -= label * math.log(s) + (1 - label) * math.log(1 - s)
        match += nll / count
        weight += bce / 10
    torch.testing.assert_close(losses["score"].detach(), score)
    torch.testing.assert_close(float(losses["match"]), match)
    torch.testing.assert_close(float(losses["weight"]), weight)
    torch.testing.assert_close(losses["loss"], losses["score"] + losses["match"] + losses["weight"])


def test_entropy_target_is_detached() -> None:
    result = _crafted_result()
    losses = _model().training_losses(result, RegistrationBatch(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3)))
    inputs = [result.aux["similarity"], result.aux["scores_src"]]
    grad_sim, grad_scores = torch.autograd.grad(losses["score"], inputs, allow_unused=True)
    assert grad_sim is None and grad_scores is not None and grad_scores.abs().max() > 0


def test_validation_labels_come_from_the_ground_truth(batch: RegistrationBatch) -> None:
    model = _model().eval()
    result = model(batch.points_src, batch.points_ref)
    losses = model.training_losses(result, batch)
    assert all(torch.isfinite(v) for v in losses.values())
    # Same clouds as the reference: the loss labels are the nearest kept reference points under the GT.
    labels, positive = model._match_labels(result, batch)
    gt = batch.transform_ref_src
    assert gt is not None
    for b in range(3):
        moved = se3.transform_points(gt[b : b + 1], batch.points_src[b : b + 1, result.aux["index_src"][b]])[0]
        dist = torch.cdist(moved, batch.points_ref[b, result.aux["index_ref"][b]])
        assert torch.equal(labels[b], dist.argmin(1)) and torch.equal(positive[b], dist.min(1).values < 0.05)


# --- configs -----------------------------------------------------------------------------------------------------
def test_config_follows_the_original() -> None:
    # Every composition (with/without configs/lc.yaml, each data file) is built in tests/test_method_configs.py.
    plain = yaml.safe_load((CONFIGS / "models" / "idam.yaml").read_text())
    args = plain["model"]["init_args"]
    assert plain["model"]["class_path"] == "lcreg.baselines.idam.IDAM"
    assert (args["emb_dims"], args["k"], args["num_iters"], args["num_kept"], args["positive_threshold"]) == (
        64,
        12,
        3,
        None,
        0.05,
    )
    assert args["optimizer"]["init_args"] == {"lr": 0.0001, "weight_decay": 0.001}
    assert args["lr_scheduler"]["init_args"] == {"milestones": [30], "gamma": 0.1}
    assert plain["trainer"]["max_epochs"] == 40  # batch 16: tests/test_method_configs.py::test_original_batch_sizes


# --- unit invariance (issue 14, defect 8) ------------------------------------------------------------------------
def _unit_pair() -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    # float64: an untrained IDAM turns float32 rounding (1e-7) into other arg-max matches; the scaling is exact here.
    src = torch.rand(2, 128, 3, generator=gen, dtype=torch.float64) - 0.5
    angles = torch.tensor([[0.3, 0.2, 0.1], [0.1, -0.2, 0.4]], dtype=torch.float64)
    from lcreg.geometry.euler import euler_zyx_to_matrix

    return src, src @ euler_zyx_to_matrix(angles).transpose(1, 2) + 0.05


@pytest.mark.parametrize("scale", [1e-3, 1e-1, 1e2, 1e4, 1e6])
def test_register_does_not_depend_on_the_unit(scale: float) -> None:
    # Before: ValueError "`weights` must have a positive sum" at 1e6 (an argument the caller never passed), and a
    # different rotation at every scale.
    torch.manual_seed(0)
    model = IDAM().eval()
    src, ref = _unit_pair()
    base = model.register(src, ref).transform_ref_src
    scaled = model.register(src * scale, ref * scale).transform_ref_src
    torch.testing.assert_close(scaled[:, :3, :3], base[:, :3, :3], atol=1e-4, rtol=0.0)
    torch.testing.assert_close(scaled[:, :3, 3] / scale, base[:, :3, 3], atol=1e-4, rtol=0.0)


def test_raw_coordinates_at_1e6_do_not_underflow_the_weights() -> None:
    torch.manual_seed(0)
    src, ref = _unit_pair()
    out = IDAM(unit_scale=None).eval().register(src * 1e6, ref * 1e6).transform_ref_src
    assert torch.isfinite(out).all()


def test_hybrid_weights_are_unchanged_and_never_all_zero() -> None:
    logits = torch.randn(3, 40, generator=torch.Generator().manual_seed(0)) * 5
    plain = torch.sigmoid(logits)
    plain = plain * (plain >= plain.median(dim=1, keepdim=True).values)
    torch.testing.assert_close(hybrid_weights(logits), plain / plain.sum(dim=1, keepdim=True))
    huge = hybrid_weights(logits * 1e4 - 1e6)  # every sigmoid underflows to 0 in float32
    assert torch.isfinite(huge).all() and torch.allclose(huge.sum(dim=1), torch.ones(3))


@pytest.mark.parametrize("value", [0.0, -1.0, float("inf"), float("nan"), "1"])
def test_unit_scale_is_checked(value: object) -> None:
    with pytest.raises(ValueError, match="unit_scale"):
        IDAM(unit_scale=value)  # type: ignore[arg-type]
