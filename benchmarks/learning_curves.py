"""Learning curves of training variants on ModelNet40 validation pairs (never test), several seeds each.

    python benchmarks/learning_curves.py --root ../shared/data/modelnet40_mini --points 1024 --steps 500 \
        --val-every 50 --seeds 0 1 2 --run-dir runs/learning_curves --out docs/results/learning_curves.md
    python benchmarks/learning_curves.py --root ../shared/data/modelnet40_mini --points 1024 --steps 3000 \
        --val-every 50 --patience 8 --val-pairs 4 --seeds 0 1 2 --variants selfsup --run-dir runs/converge/lc
    python benchmarks/learning_curves.py --smoke      # seconds, embedded shapes, 2 steps

Every (variant, seed) is one ``lcreg fit`` (:func:`lcreg.experiments.benchmarking.fit`) that first validates its
initial weights (step 0), then validates every ``--val-every`` steps; checkpoints are chosen on ``val/rre_mean_deg``.
The step-0 weights are a candidate too (since session 31; file ``step000000-...``): a run that never beats the weights
it started from (a pretrained encoder that training only spoils) selects them, and its patience counts from them.
Each run's ``metrics.csv`` (losses, the IC-LK Jacobian diagnostics ``train/j_*``, validation registration) is kept under
``--run-dir/<variant>/seed<k>``. Finished runs are listed in ``<run-dir>/runs.jsonl`` and skipped on a rerun, so a
long study can be run in chunks.

**Converge budget** (``--patience P``): each run trains until the validation error
(:data:`lcreg.experiments.benchmarking.CONVERGE_METRIC`, the mean of min(RRE, 5°)) has not improved for ``P``
validations, capped by ``--steps``; the best checkpoint is chosen on the same metric. ``--val-pairs K`` draws K
validation pairs from every validation object (``val_pairs_per_object``: 4 gives 312 pairs on ``modelnet40_mini``), so
one failed pair moves the criterion by at most 5° / 312. A run that was cut off (killed, session over) resumes from its
``last.ckpt`` on the next call with the same arguments, early-stopping state included. ``--monitor
val/pose_clip_r2_t0p01`` stops and selects on the translation-aware error instead (the mean of
min(max(RRE / 2°, RTE / 0.01), 2.5), :class:`lcreg.metrics.registration.PoseErrorClippedMean`: below 1 exactly for the
pairs within recall (2°, 0.01)); such runs are keyed apart (``converge p<P> v<K> m<metric>``). ``--min-steps M``
lets no run stop early before step M (Lightning's ``min_steps``; such runs are keyed ``... min<M>``): for a method
whose validation error sits on a plateau longer than the patience before it falls (iPCRNet's average-rotation
plateau); ``--min-steps`` equal to ``--steps`` trains every run to the cap and still selects on ``--monitor``.

``--jobs N`` trains N runs at once, each (variant, seed) in its own process of this script (a lent GPU: one run of
256 points x 8 leaves an H100 mostly idle; the training queue's ``--jobs`` passes it on, as to ``lcreg reproduce``).

``--out x.md`` writes the summary table of every finished run of the chosen variants
(:func:`lcreg.experiments.benchmarking.summary_table`) and the PNGs beside it (``x_validation.png``,
``x_jacobian.png``, ... by :func:`lcreg.experiments.benchmarking.plot_curves`, as
``benchmarks/plot_learning_curves.py`` draws them); ``--report-only`` writes them without training anything (e.g. from
the committed copy of a queue job's runs); ``--also-runs DIR ...`` adds the finished runs of other run folders to the
report (e.g. a lever job against the recipe runs of an earlier job).

Variants (same batch 16, pair stream and validation pairs; the ``--seeds`` seed fixes initialisation and order): model A
and D are the paper's objective exactly as written (``configs/ablation/model_A.yaml``,
``configs/dvds_modelnet40.yaml``); the label-free recipe adds :class:`~lcreg.models.loss_terms.SelfMotionLoss`
(``configs/dvds_selfsup_modelnet40.yaml``); PointNetLK is the supervised control (analytic Jacobian, lr 1e-4, gradient
clipping 1, as in issue 12's table); ``pointnetlk_nobn`` is the same without BatchNorm (like the DVDs encoder: the solve
then sees the same function as the training pass), ``pointnetlk_nobn_steplr`` that with the lr halved every 5 epochs
(its validation mean RRE rose after step 500 at a constant lr); ``pointnetlk_orig`` is
``configs/models/pointnetlk.yaml`` as it stands, the original's settings (BatchNorm with its running statistics
refreshed before each solve, finite-difference Jacobian, Adam lr 1e-3, no clipping), which FMR-Net shares;
``pointnetlk_fmrinit`` is ``pointnetlk`` (BatchNorm, supervised settings) starting from FMR-Net's reconstruction-trained
encoder (``encoder_from``, :data:`FMR_SEED0_WEIGHTS`), as the original starts from a classifier's (``--transfer-from``).
``selfsup_lr3e-5`` and ``selfsup_steplr`` are the recipe at lr 3e-5 and with the lr halved every 5 epochs (the levers of
issue 23); ``selfsup_tw25`` weighs the self-motion term's translation error 25 times (a 0.01 error like a 2 deg one, the
recall thresholds), ``selfsup_tw100`` 100 times, ``selfsup_tw400`` 400 times; ``selfsup_tw100_fine`` adds to
``selfsup_tw100`` a second self-motion term on small motions (Euler U[0, 2 deg], t U[-0.02, 0.02], translation weighted
100: the errors left after the coarse solve, at the recall thresholds' scale); ``selfsup_tw100_stat`` adds to
``selfsup_tw100`` :class:`~lcreg.models.loss_terms.SelfMotionStationarityLoss` on the same kind of pairs (translation
weighted 100): one IC-LK update started at the known motion should not move (started at the true test pose, the shipped
DVDs file ends at the recall it reaches from the identity: the descriptor's minimum is biased); ``selfsup_frac50`` draws
its two samplings from half the cloud each (they share half their points, as two independent samplings of 1024 of
ModelNet40's 2048 points do; the recipe's 0.75 shares three quarters); ``pcrnet`` and ``fmr`` are those baselines with
their own configs (``configs/models/``), at the batch and points given here; ``pcrnet_idinit`` starts iPCRNet's every
delta pose at the identity (on 8 fixed pairs, ``benchmarks/overfit.py``, the reference initialisation's Chamfer descent
ends at rotations 90-180 deg away, the identity start fits them), ``pcrnet_idinit_lr1e-4`` the same at the original
TensorFlow code's lr 1e-4 (at 1e-3, 2 of 3 runs collapsed to one constant update with dead ReLUs,
``benchmarks/pcrnet_collapse.py``), ``fmr_semi`` is FMR-Net's semi-supervised variant (the original's ``--train-type
1``: the pose term beside the reconstruction; trained on its reconstruction alone, FMR-Net's IC-LK stops registering the
fixed pairs, though on unseen pairs it improves), ``fmr_tw100`` is FMR-Net with ``selfsup_tw100``'s self-motion term
added to its reconstruction (label-free; a goal (c) probe: FMR-Net's descriptor keeps more pairs at the true pose than
DVDs', its solve falls into more wrong basins); ``selfsup_tw100_bn`` is ``selfsup_tw100`` with FMR-Net's BatchNorm in
the encoder (the other candidate for that difference), ``selfsup_tw100_bn_mlpdec`` the same with FMR-Net's MLP decoder
in place of FoldingNet (``DVDs(decoder="mlp")``: FMR-Net's objective on DVDs' network with FoldingNet kept a more biased
descriptor than FMR-Net's own), ``selfsup_tw100_bn_fmrinit`` the same starting from FMR-Net's encoder as
``pointnetlk_fmrinit`` does (does DVDs' objective keep a descriptor whose fixed point is unbiased?);
``model_D_bn_lr1e-3`` is the paper's model D (its objective as written, no self-motion term) with FMR-Net's optimiser
settings, BatchNorm in the encoder and Adam lr 1e-3
(``configs/models/dvds.yaml`` turned both off on evidence of a few hundred steps; FMR-Net with them dips early, then
reaches ICP's recall on the test pairs with starts); ``aux_only_bn_lr1e-3`` keeps of it only DVDs' auxiliary tasks
(folding reconstruction 0.5, normals 0.1: no global residual, no LC), FMR-Net's kind of objective with DVDs' own
decoder and normal head; ``recon_sq_bn_lr1e-3`` is FMR-Net's whole training objective on DVDs' network, all but its
decoder: the reconstruction alone, weight 1, with FMR-Net's squared Chamfer, no normal head, no gradient clipping
(``aux_only_bn_lr1e-3``'s descriptor, started at the exact truth, keeps 70.5 % of the validation pairs within (2 deg,
0.01), FMR-Net's 92-93 %: the objective's details or the decoder?); ``recon_sq_bn_lr1e-3_mlpdec`` is the same with
FMR-Net's MLP decoder too, so FMR-Net's objective and decoder on DVDs' encoder (does DVDs' code path give FMR-Net's
descriptor?). ``prnet`` is PRNet as in ``lcreg reproduce lc``
(``configs/models/prnet.yaml``, the DCP-family pairs of ``configs/data/dcp_protocol.yaml``, Adam lr 1e-3 at upstream's
batch 36); ``prnet_lr2.2e-4`` scales that learning rate linearly to a batch of 8 (1e-3 x 8 / 36): at batch 8 and lr 1e-3
every PRNet run of the converge budget got worse after a few hundred steps. ``dcp`` is DCP-v2 as in ``lcreg reproduce
lc`` (the same pairs), ``dcp_nobn`` the same without BatchNorm in its DGCNN: trained on 8 fixed pairs
(``benchmarks/overfit.py``), DCP-v2 fits them in training mode but not in eval mode, where BatchNorm's running
statistics replace the batch's own. ``prnet_lr2.2e-4_nobn`` asks the same of PRNet (without BatchNorm in its DGCNN and
TemperatureNet): evaluated with each batch's own statistics, its lr-2.2e-4 checkpoint registers the validation pairs
better than in eval mode (``docs/results/converge/prnet_lr_256/probes/``). """

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

from lcreg.experiments.benchmarking import (
    CONVERGE_METRIC,
    SELECTION_METRIC,
    ResultLog,
    Values,
    add_smoke_argument,
    apply_smoke,
    cli_args,
    converge_overrides,
    fit,
    fit_overrides,
    load_runs,
    machine_line,
    machines_of,
    markdown_table,
    output_path,
    peak_memory_mib,
    plot_curves,
    summary_table,
    synthetic_overrides,
    training_device,
    write_text,
)
from lcreg.experiments.reproduce.parallel import WorkerRun, WorkersFailedError, run_workers


class Variant(NamedTuple):
    """A training variant: registry method, extra config files (relative to ``configs/``) and values by dotted key."""

    method: str
    configs: tuple[str, ...] = ()
    overrides: Mapping[str, Any] = MappingProxyType({})


SUPERVISED_LK = {  # PointNetLK as in issue 12's table: analytic Jacobian, lr 1e-4, gradient clipping 1
    "model.init_args.jacobian": "analytic",
    "model.init_args.optimizer.init_args.lr": 0.0001,
    "trainer.gradient_clip_val": 1.0,
}
FMR_SEED0_WEIGHTS = Path(__file__).resolve().parents[1] / "docs/results/converge/fmr_1024/best/fmr-seed0.pt"
"""FMR-Net's reconstruction-trained encoder (``fmr_1024`` seed 0: the lowest validation median RRE of its seeds)."""
HALVE_EVERY_5_EPOCHS = {
    "model.init_args.lr_scheduler": {
        "class_path": "torch.optim.lr_scheduler.StepLR",
        "init_args": {"step_size": 5, "gamma": 0.5},
    }
}
FMR_OPTIMISATION = MappingProxyType(
    {"model.init_args.batch_norm": True, "model.init_args.optimizer.init_args.lr": 0.001}
)
"""FMR-Net's encoder BatchNorm and Adam learning rate (``configs/models/fmr.yaml``), for a DVDs variant."""
RECIPE_SELF_MOTION = {"max_angle_deg": 45.0, "max_translation": 0.5, "sample_fraction": 0.75}  # self_motion.yaml


FINE_SELF_MOTION = {"name": "self_motion_fine", "max_angle_deg": 2.0, "max_translation": 0.02}
"""A second self-motion term on motions at the scale of the recall thresholds (2 deg, 0.01): what is left after
the coarse solve, where the precision of goal (c) is decided."""


def recipe_with(*extra_motions: Mapping[str, Any], **self_motion: float) -> Variant:
    """The recipe (``configs/dvds_selfsup_modelnet40.yaml``) with some of its self-motion term's arguments changed.

    Args:
        *extra_motions: ``SelfMotionLoss`` arguments of further self-motion terms, appended after the recipe's.
        **self_motion: Arguments of the recipe's self-motion term that change.
    """
    motions = [{**RECIPE_SELF_MOTION, **self_motion}, *map(dict, extra_motions)]
    terms = [
        {"class_path": "lcreg.models.loss_terms.LocalConsistencyLoss"},  # configs/lc.yaml: the defaults
        *({"class_path": "lcreg.models.loss_terms.SelfMotionLoss", "init_args": args} for args in motions),
    ]
    return Variant("dvds_selfsup", overrides={"model.init_args.loss_terms": terms})


SELF_MOTION_TW100 = recipe_with(translation_weight=100.0).overrides["model.init_args.loss_terms"][-1]
"""``selfsup_tw100``'s self-motion term alone, for a host other than DVDs (``fmr_tw100``: FMR-Net's reconstruction
plus the term; its descriptor's fixed point is less biased than DVDs', its wrong-basin tail worse)."""


STATIONARITY = {
    "class_path": "lcreg.models.loss_terms.SelfMotionStationarityLoss",
    "init_args": {**RECIPE_SELF_MOTION, "translation_weight": 100.0},
}
"""The fixed-point term on the recipe's self-motion pairs, translation weighted as ``selfsup_tw100``'s."""


def with_overrides(variant: Variant, overrides: Mapping[str, Any]) -> Variant:
    """``variant`` with more (or changed) configuration values."""
    return variant._replace(overrides={**variant.overrides, **overrides})


def plus_terms(variant: Variant, *terms: Mapping[str, Any]) -> Variant:
    """``variant`` (a :func:`recipe_with` one) with more loss terms appended after its own."""
    own = variant.overrides["model.init_args.loss_terms"]
    return with_overrides(variant, {"model.init_args.loss_terms": [*own, *map(dict, terms)]})


SELFSUP_TW100_BN = with_overrides(recipe_with(translation_weight=100.0), {"model.init_args.batch_norm": True})
"""The self-motion recipe, translation weighted 100, with FMR-Net's BatchNorm in the encoder (goal (c) probes)."""

MLP_DECODER = {"model.init_args.decoder": "mlp", "model.init_args.decoder_hidden": [1024, 512, 256]}
"""FMR-Net's decoder (widths 1024-512-256) in place of DVDs' FoldingNet."""
RECON_SQ_BN = with_overrides(
    Variant("dvds", overrides=FMR_OPTIMISATION),
    {
        "model.init_args.lambda_global": 0,
        "model.init_args.loss_terms": [],
        "model.init_args.lambda_normal": 0,
        "model.init_args.lambda_recon": 1.0,
        "model.init_args.squared_chamfer": True,
        "trainer.gradient_clip_val": None,
    },
)
"""FMR-Net's training objective on DVDs' network: its reconstruction alone (squared Chamfer, weight 1), optimiser."""


RECIPE_TERMS = ("global", "lc", "self_motion", "normal")
"""The recipe's terms beyond FMR-Net's reconstruction, by name (:func:`recon_mlp_with_recipe_terms`)."""


def recon_mlp_with_recipe_terms(scale: float, terms: Sequence[str] = RECIPE_TERMS) -> Variant:
    """FMR-Net's objective and decoder on DVDs (``recon_sq_bn_lr1e-3_mlpdec``) plus the recipe's terms of
    ``selfsup_tw100`` named in ``terms`` (:data:`RECIPE_TERMS`: global residual, LC, self-motion with translation
    weight 100, normals), each at ``scale`` times its weight in the recipe (1, 1, 1, 0.1); the others off.
    """
    if unknown := set(terms) - set(RECIPE_TERMS):
        raise ValueError(f"unknown recipe terms {sorted(unknown)}; known: {RECIPE_TERMS}")
    lc, self_motion = recipe_with(translation_weight=100.0).overrides["model.init_args.loss_terms"]
    kept = [term for name, term in (("lc", lc), ("self_motion", self_motion)) if name in terms]
    weighted = [{**term, "init_args": {**term.get("init_args", {}), "weight": scale}} for term in kept]
    weights = {
        "model.init_args.lambda_global": scale if "global" in terms else 0,
        "model.init_args.lambda_normal": 0.1 * scale if "normal" in terms else 0,
    }
    return with_overrides(RECON_SQ_BN, {**MLP_DECODER, **weights, "model.init_args.loss_terms": weighted})


VARIANTS: dict[str, Variant] = {
    "model_A": Variant("dvds", ("ablation/model_A.yaml",)),
    "model_D": Variant("dvds"),
    "selfsup": Variant("dvds_selfsup"),
    "self_motion_only": Variant(
        "dvds",
        (),
        {
            "model.init_args.loss_terms": [{"class_path": "lcreg.models.loss_terms.SelfMotionLoss"}],  # replaces LC
            "model.init_args.lambda_global": 0,
            "model.init_args.lambda_recon": 0,
            "model.init_args.lambda_normal": 0,
        },
    ),
    "pointnetlk": Variant("pointnetlk", overrides=SUPERVISED_LK),
    "selfsup_lr3e-5": Variant("dvds_selfsup", overrides={"model.init_args.optimizer.init_args.lr": 3e-05}),
    "selfsup_steplr": Variant("dvds_selfsup", overrides=HALVE_EVERY_5_EPOCHS),
    "selfsup_tw25": recipe_with(translation_weight=25.0),
    "selfsup_tw100": recipe_with(translation_weight=100.0),
    "selfsup_tw400": recipe_with(translation_weight=400.0),
    "selfsup_tw100_fine": recipe_with({**FINE_SELF_MOTION, "translation_weight": 100.0}, translation_weight=100.0),
    "selfsup_tw100_stat": plus_terms(recipe_with(translation_weight=100.0), STATIONARITY),
    "selfsup_tw100_bn": SELFSUP_TW100_BN,
    "selfsup_tw100_bn_mlpdec": with_overrides(SELFSUP_TW100_BN, MLP_DECODER),
    "selfsup_tw100_bn_fmrinit": with_overrides(
        SELFSUP_TW100_BN, {"model.init_args.encoder_from": str(FMR_SEED0_WEIGHTS)}
    ),
    "model_D_bn_lr1e-3": Variant("dvds", overrides=FMR_OPTIMISATION),
    "aux_only_bn_lr1e-3": with_overrides(
        Variant("dvds", overrides=FMR_OPTIMISATION),
        {"model.init_args.lambda_global": 0, "model.init_args.loss_terms": []},
    ),
    "recon_sq_bn_lr1e-3": RECON_SQ_BN,
    "recon_sq_bn_lr1e-3_mlpdec": with_overrides(RECON_SQ_BN, MLP_DECODER),
    "recon_mlp_recipe0.1": recon_mlp_with_recipe_terms(0.1),
    "recon_mlp_recipe0.01": recon_mlp_with_recipe_terms(0.01),
    **{f"recon_mlp_{n}{x}": recon_mlp_with_recipe_terms(x, (n,)) for n in RECIPE_TERMS for x in (0.1, 0.01)},
    "recon_mlp_global1": recon_mlp_with_recipe_terms(1.0, ("global",)),
    "recon_sq_bn_lr1e-3_mlpdec_percloud": with_overrides(
        RECON_SQ_BN, {**MLP_DECODER, "model.init_args.norm_batch": "per_cloud"}
    ),
    "selfsup_frac50": recipe_with(sample_fraction=0.5),
    "pcrnet": Variant("pcrnet"),
    "pcrnet_idinit": Variant("pcrnet", overrides={"model.init_args.identity_init": True}),
    "pcrnet_idinit_lr1e-4": Variant(
        "pcrnet", overrides={"model.init_args.identity_init": True, "model.init_args.optimizer.init_args.lr": 1e-4}
    ),
    "fmr": Variant("fmr"),
    "fmr_semi": Variant("fmr", overrides={"model.init_args.pose_weight": 1.0}),
    "fmr_tw100": Variant("fmr", overrides={"model.init_args.loss_terms": [SELF_MOTION_TW100]}),
    "pointnetlk_orig": Variant("pointnetlk"),
    "pointnetlk_nobn": Variant("pointnetlk", overrides={"model.init_args.batch_norm": False, **SUPERVISED_LK}),
    "pointnetlk_fmrinit": Variant(
        "pointnetlk", overrides={"model.init_args.encoder_from": str(FMR_SEED0_WEIGHTS), **SUPERVISED_LK}
    ),
    "pointnetlk_nobn_steplr": Variant(
        "pointnetlk", overrides={"model.init_args.batch_norm": False, **SUPERVISED_LK, **HALVE_EVERY_5_EPOCHS}
    ),
    "prnet": Variant("prnet"),
    "prnet_lr2.2e-4": Variant("prnet", overrides={"model.init_args.optimizer.init_args.lr": 2.2e-4}),
    "prnet_lr2.2e-4_nobn": Variant(
        "prnet", overrides={"model.init_args.optimizer.init_args.lr": 2.2e-4, "model.init_args.batch_norm": False}
    ),
    "dcp": Variant("dcp"),
    "dcp_nobn": Variant("dcp", overrides={"model.init_args.batch_norm": False}),
}
SMOKE = {"steps": 2, "val_every": 1, "seeds": [0], "variants": ["model_D", "selfsup"]}
MONITORS = (CONVERGE_METRIC, "val/pose_clip_r2_t0p01", "val/rre_median_deg")
"""What ``--monitor`` may stop and select a converge run on: the rotation-only clipped error, the translation-aware
one of recall (2°, 0.01) (:class:`lcreg.metrics.registration.PoseErrorClippedMean`), or the median RRE (the rule of
DCP-v2 and PRNet in ``lcreg reproduce lc --budget converge``, whose errors sit near 5°, where the clipped mean is
flat)."""

KEY = ("variant", "seed", "points", "steps", "budget")
"""A run's identity in ``runs.jsonl``: ``budget`` is ``None`` for a fixed step budget (the rows of earlier versions),
``"converge p<P> v<K>"`` for a converge run."""


def data_overrides(args: argparse.Namespace) -> Values:
    """The data of every run: ModelNet40 at ``--points`` and batch 16, or tiny embedded shapes (``--smoke``)."""
    if args.root is None:
        return synthetic_overrides(pairs=4, num_points=64, batch_size=2)
    values = {"root": args.root, "num_points": args.points, "batch_size": args.batch, "num_workers": 0}
    if args.val_pairs != 1:
        values["val_pairs_per_object"] = args.val_pairs
    return cli_args("data", values)


def other_monitor(args: argparse.Namespace) -> str | None:
    """The ``--monitor`` of a converge run when it is not :data:`CONVERGE_METRIC` (such runs are keyed apart)."""
    return None if args.patience is None or args.monitor == CONVERGE_METRIC else args.monitor


def budget_key(args: argparse.Namespace) -> str | None:
    """``None`` for a fixed step budget, ``"converge p<P> v<K>"`` for a converge run (see :data:`KEY`).

    A converge run on another ``--monitor`` than :data:`CONVERGE_METRIC` appends ``" m<monitor>"``, one with
    ``--min-steps`` then ``" min<M>"``.
    """
    if args.patience is None:
        return None
    metric = "" if (monitor := other_monitor(args)) is None else f" m{monitor}"
    floor = "" if args.min_steps is None else f" min{args.min_steps}"
    return f"converge p{args.patience} v{args.val_pairs}{metric}{floor}"


def run_folder(args: argparse.Namespace, name: str) -> str:
    """The folder of variant ``name``'s runs under ``--run-dir``: ``name``, or ``name@<metric>`` on another
    ``--monitor`` (a converge run resumes from its folder's ``last.ckpt``: runs on two monitors must not share one)."""
    monitor = other_monitor(args)
    return name if monitor is None else f"{name}@{monitor.rsplit('/', 1)[-1]}"


def training_overrides(args: argparse.Namespace, run_dir: Path, seed: int) -> Values:
    """The step budget of every run: fixed, or until ``--patience`` validations bring no improvement (not before
    ``--min-steps``)."""
    if args.patience is None:
        return fit_overrides(args.steps, args.val_every, run_dir, name="", seed=seed)
    values = converge_overrides(
        args.steps, args.val_every, args.patience, run_dir, name="", seed=seed, monitor=args.monitor
    )
    return values if args.min_steps is None else {**values, "trainer.min_steps": args.min_steps}


def run_key(args: argparse.Namespace, name: str, seed: int) -> dict[str, Any]:
    """The identity of run (``name``, ``seed``) in ``runs.jsonl`` (:data:`KEY`)."""
    return {"variant": name, "seed": seed, "points": args.points, "steps": args.steps, "budget": budget_key(args)}


def worker_runs(args: argparse.Namespace, log: ResultLog) -> list[WorkerRun]:
    """``--jobs``: one process of this script per unfinished (variant, seed), with this call's budget and run folder.

    Each appends its row to the shared ``runs.jsonl`` and logs to ``<run folder>/seed<k>/worker.log``; an empty
    ``--root`` is the embedded shapes (``--smoke``), as any ``--root`` that is not a folder.
    """
    options = [
        *("--root", args.root or "", "--points", str(args.points), "--batch", str(args.batch)),
        *("--steps", str(args.steps), "--val-every", str(args.val_every), "--val-pairs", str(args.val_pairs)),
        *("--monitor", args.monitor, "--run-dir", str(args.run_dir)),
        *(() if args.patience is None else ("--patience", str(args.patience))),
        *(() if args.min_steps is None else ("--min-steps", str(args.min_steps))),
    ]
    return [
        WorkerRun(
            f"{name} seed {seed}",
            (sys.executable, str(Path(__file__).resolve()), *options, "--variants", name, "--seeds", str(seed)),
            Path(args.run_dir) / run_folder(args, name) / f"seed{seed}" / "worker.log",
        )
        for name in args.variants
        for seed in args.seeds
        if not log.done(**run_key(args, name, seed))
    ]


def run(args: argparse.Namespace, name: str, seed: int, log: ResultLog) -> None:
    """Train ``name`` from seed ``seed`` unless ``log`` lists it as finished; append its row when done.

    A converge run that was cut off resumes from its ``last.ckpt``.
    """
    key = run_key(args, name, seed)
    if log.done(**key):
        print(f"{name} seed {seed}: done before, skipped", flush=True)
        return
    variant = VARIANTS[name]
    run_dir = Path(args.run_dir) / run_folder(args, name)
    values = {
        **data_overrides(args),
        **training_overrides(args, run_dir, seed),
        "trainer.logger.init_args.version": f"seed{seed}",
        **variant.overrides,
    }
    converge = args.patience is not None
    monitor = args.monitor if converge else SELECTION_METRIC
    result, peak_mib = peak_memory_mib(
        lambda: fit(variant.method, values, variant.configs, validate_first=True, monitor=monitor, resume=converge),
        training_device(),
    )
    metrics = Path(result.trainer.log_dir or run_dir) / "metrics.csv"
    stopped = result.trainer.global_step
    row = {**key, "metrics_csv": str(metrics), "best_checkpoint": str(result.best_checkpoint)}
    # The machine and peak memory of this call (a resumed run: of its last segment), as the sweeps' rows record them.
    machine = {"machine": machine_line(result.trainer.strategy.root_device), "peak_mib": peak_mib}
    log.append(
        {
            **row,
            "seconds": round(result.seconds, 1),
            "stopped_step": stopped,
            "early_stopped": stopped < args.steps,
            **machine,
        }
    )
    print(f"{name} seed {seed}: {result.seconds:.0f} s, stopped at step {stopped}, {metrics}", flush=True)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--val-every", type=int, default=50)
    parser.add_argument(
        "--patience", type=int, default=None, help="converge budget: stop after this many validations without gain"
    )
    parser.add_argument(
        "--min-steps",
        type=int,
        default=None,
        help="converge budget: no early stop before this step (a plateau longer than the patience); <= --steps",
    )
    parser.add_argument("--val-pairs", type=int, default=1, help="validation pairs per validation object")
    parser.add_argument(
        "--monitor",
        default=CONVERGE_METRIC,
        choices=MONITORS,
        help="converge budget: the validation metric that stops the run and selects its checkpoint",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--run-dir", default="runs/learning_curves")
    parser.add_argument("--out", default=None, help="summary table (.md); the PNGs are written beside it")
    parser.add_argument(
        "--report-only", action="store_true", help="only write --out from the finished runs (train nothing)"
    )
    parser.add_argument(
        "--also-runs",
        nargs="*",
        default=[],
        metavar="DIR",
        help="more run folders whose finished runs join the report (e.g. another queue job's committed runs)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="runs trained at once, each in its own process of this script (a GPU takes several; default 1)",
    )
    add_smoke_argument(parser)
    args = apply_smoke(parser.parse_args(argv), SMOKE)
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    if args.min_steps is not None and (args.patience is None or not 0 < args.min_steps <= args.steps):
        parser.error(f"--min-steps needs --patience and 0 < M <= --steps ({args.steps}), got {args.min_steps}")
    if args.smoke and args.run_dir == parser.get_default("run_dir"):
        args.run_dir = tempfile.mkdtemp(prefix="lcreg-smoke-")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    log = ResultLog(Path(args.run_dir) / "runs.jsonl", key=KEY)
    budget = budget_key(args) or "fixed budget"
    machine = machine_line(training_device())
    print(f"{args.points} points, {args.steps} steps ({budget}), seeds {args.seeds}; {machine}", flush=True)
    failure = None
    if args.report_only:
        pass
    elif args.jobs > 1:
        try:
            run_workers(worker_runs(args, log), args.jobs, lambda line: print(line, flush=True))
        except WorkersFailedError as err:  # the finished runs are reported first
            failure = err
        log = ResultLog(log.path, key=KEY)  # the workers' rows
    else:
        for name in args.variants:
            for seed in args.seeds:
                run(args, name, seed, log)
    out = output_path(args.out, "learning_curves.md", args.smoke)
    if out:
        report(args, log, out)
    if failure is not None:
        print(failure, file=sys.stderr, flush=True)
        raise SystemExit(failure.exit_code)


def stops_table(rows: Sequence[dict[str, Any]]) -> str:
    """Where every run stopped (early stop or the step cap), its selected checkpoint, training time and peak memory.

    Time and memory are of the run's last call (a resumed run: its last segment); rows written before rows recorded
    memory show ``-``.
    """
    header = ["variant", "seed", "stopped at step", "why", "selected checkpoint", "train s", "peak MiB", "machine"]
    body = [
        [
            row["variant"],
            str(row["seed"]),
            str(row.get("stopped_step", "-")),
            "early stop" if row.get("early_stopped") else "step cap",
            Path(row["best_checkpoint"]).name,
            f"{row['seconds']:.0f}",
            "-" if row.get("peak_mib") is None else f"{row['peak_mib']:.0f}",
            row.get("machine", "-"),
        ]
        for row in rows
    ]
    return markdown_table(header, body)


def metrics_file(run_dir: Path, row: dict[str, Any]) -> Path:
    """A finished run's ``metrics.csv``: the recorded path, or the same run (its last three path parts,
    ``<folder>/seed<k>/metrics.csv``) under ``run_dir`` (a copied folder, e.g. the committed results of the queue)."""
    recorded = Path(row["metrics_csv"])
    return (
        recorded if recorded.is_file() else run_dir / recorded.parent.parent.name / recorded.parent.name / recorded.name
    )


def report(args: argparse.Namespace, log: ResultLog, out: Path) -> None:
    """Summary table and learning-curve PNGs of the finished runs of ``args.variants`` at this budget."""
    files: dict[str, list[str]] = {}
    finished = []
    wanted = (args.points, args.steps, budget_key(args))
    sources = [(Path(args.run_dir), log.rows)]
    sources += [(Path(d), ResultLog(Path(d) / "runs.jsonl", key=KEY).rows) for d in args.also_runs]
    for run_dir, rows in sources:
        for row in rows:
            if row["variant"] in args.variants and (row["points"], row["steps"], row.get("budget")) == wanted:
                files.setdefault(row["variant"], []).append(str(metrics_file(run_dir, row)))
                finished.append(row)
    runs = load_runs({variant: files[variant] for variant in args.variants if variant in files})
    budget = budget_key(args) or "fixed budget"
    head = f"{args.points} points, {args.steps} steps ({budget}), batch {args.batch}; {machines_of(finished)}"
    head += f"; runs: {', '.join(str(d) for d, _ in sources)}"
    write_text(out, "\n".join([head, "", summary_table(runs), "", stops_table(finished), ""]))
    for path in plot_curves(runs, out.parent, prefix=f"{out.stem}_"):
        print(f"wrote {path}", flush=True)
    print(f"wrote {out}", flush=True)


if __name__ == "__main__":
    main()
