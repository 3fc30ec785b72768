"""Every registration method of lcreg, once: the table that ``register``, ``pretrained`` and the experiments read.

A method is a class (a :class:`~lcreg.models.base.RegistrationModule`), its config under lcreg's configs
(``configs/models/<name>.yaml``, :func:`lcreg.config.configs_root`) and, for learned methods, the names of its
pretrained weights. This module holds strings only (no torch, no Lightning), so reading it is free; the class is
imported by whoever builds it.

``lcreg.registration.methods`` derives ``register``'s method names from :data:`METHODS`, :mod:`lcreg.weights` checks a
weights name against its method's class, ``lcreg/__init__`` exports each class lazily, and
``lcreg.experiments.benchmarking.registry`` builds its table rows (a method plus data, refinement, LC, batch) on these
names.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["METHODS", "MethodInfo", "class_names", "learned_methods", "method_of_class", "pretrained_weights"]


@dataclass(frozen=True)
class MethodInfo:
    """One method.

    Attributes:
        name: Short name (``register --method``, config file stem, experiment rows).
        label: Name in tables and help (the paper's spelling).
        class_path: ``module.Class`` of the model.
        summary: One line for ``--help`` listings.
        learned: Whether it has weights to train.
        pretrained: Names of weights files that may ship in :mod:`lcreg.weights`, with one line each.
    """

    name: str
    label: str
    class_path: str
    summary: str
    learned: bool = True
    pretrained: tuple[tuple[str, str], ...] = ()

    @property
    def config(self) -> str:
        """Its config file relative to lcreg's configs folder."""
        return f"models/{self.name}.yaml"

    @property
    def class_name(self) -> str:
        """The class's name (``DVDs``)."""
        return self.class_path.rpartition(".")[2]

    @property
    def module(self) -> str:
        """The module defining the class."""
        return self.class_path.rpartition(".")[0]


_CLASSICAL = "lcreg.baselines.classical"
METHODS: dict[str, MethodInfo] = {
    info.name: info
    for info in (
        MethodInfo(
            "dvds",
            "DVDs",
            "lcreg.models.dvds.DVDs",
            "DVDs (this paper): PointNet descriptors + IC-LK, self-supervised",
            pretrained=(
                ("dvds-modelnet40", "DVDs trained label-free on ModelNet40 (configs/dvds_selfsup_modelnet40.yaml)"),
            ),
        ),
        MethodInfo(
            "pointnetlk",
            "PointNetLK",
            "lcreg.baselines.pointnetlk.PointNetLK",
            "PointNetLK (Aoki et al. 2019): PointNet + LK, supervised",
            pretrained=(
                (
                    "pointnetlk-modelnet40",
                    "PointNetLK with BatchNorm, analytic Jacobian, trained supervised on ModelNet40 from FMR-Net's "
                    "encoder (configs/models/pointnetlk.yaml + configs/data/modelnet40.yaml, encoder_from)",
                ),
            ),
        ),
        MethodInfo(
            "fmr",
            "FMR-Net",
            "lcreg.baselines.fmr.FMRNet",
            "FMR-Net (Huang et al. 2020): feature-metric LK",
            pretrained=(
                (
                    "fmr-modelnet40",
                    "FMR-Net trained label-free (reconstruction) on ModelNet40, analytic Jacobian, 20 IC-LK iterations "
                    "(configs/models/fmr.yaml + configs/data/modelnet40.yaml)",
                ),
            ),
        ),
        MethodInfo("dcp", "DCP-v2", "lcreg.baselines.dcp.DCP", "DCP-v2 (Wang & Solomon 2019): attention + SVD"),
        MethodInfo("prnet", "PRNet", "lcreg.baselines.prnet.PRNet", "PRNet (Wang & Solomon 2019): keypoints, partial"),
        MethodInfo("idam", "IDAM", "lcreg.baselines.idam.IDAM", "IDAM (Li et al. 2020): iterative distance-aware"),
        MethodInfo("deepgmr", "DeepGMR", "lcreg.baselines.deepgmr.DeepGMR", "DeepGMR (Yuan et al. 2020): GMM poses"),
        MethodInfo("pcrnet", "PCRNet", "lcreg.baselines.pcrnet.PCRNet", "PCRNet (Sarode et al. 2019): iterative MLP"),
        MethodInfo(
            "icp",
            "ICP",
            f"{_CLASSICAL}.ICP",
            "ICP (local; register: point-to-plane from the identity or --init)",
            learned=False,
        ),
        MethodInfo("ransac", "FPFH + RANSAC", f"{_CLASSICAL}.RANSAC", "FPFH + RANSAC (global)", learned=False),
        MethodInfo("fgr", "FPFH + FGR", f"{_CLASSICAL}.FGR", "FPFH + Fast Global Registration (global)", learned=False),
        MethodInfo(
            "kiss",
            "KISS-Matcher",
            "lcreg.baselines.kiss.KISSMatcher",
            "KISS-Matcher (global; optional: pip install 'lcreg[kiss]', Linux x86_64 / macOS arm64)",
            learned=False,
        ),
    )
}
"""Every method by short name: 8 learned, 4 classical (3 Open3D, KISS-Matcher)."""


def learned_methods() -> list[str]:
    """The names of the learned methods, in table order."""
    return [name for name, info in METHODS.items() if info.learned]


def pretrained_weights() -> dict[str, tuple[MethodInfo, str]]:
    """Every weights name any method may ship: ``name -> (method, one-line description)``."""
    return {weights: (info, text) for info in METHODS.values() for weights, text in info.pretrained}


def method_of_class(class_path: str) -> MethodInfo | None:
    """The method whose class is ``class_path`` (``None`` for another class)."""
    return next((info for info in METHODS.values() if info.class_path == class_path), None)


def class_names() -> dict[str, str]:
    """``class name -> module`` of every method (the lazy exports of ``lcreg``)."""
    return {info.class_name: info.module for info in METHODS.values()}
