"""The benchmarked rows: a library method (:data:`lcreg.methods.METHODS`) with its data, refinement, LC or recipe.

Each row names its library method; its label and model config come from that table, so a method is described once.
Config paths are relative to lcreg's ``configs/`` folder (:func:`config_dir`) and appear only here and in
:mod:`lcreg.methods`, so a new config layout is one edit. Every benchmark builds a method by name through
:func:`lcreg.experiments.benchmarking.build`, exactly as ``lcreg test --config <configs...>`` does.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeAlias

from lcreg.config import configs_root
from lcreg.methods import METHODS as LIBRARY

__all__ = [
    "ABLATION_CONFIGS",
    "DATA_CONFIGS",
    "METHODS",
    "REFINE_CONFIG",
    "VOXELIZE_CONFIG",
    "MethodSpec",
    "Values",
    "cli_args",
    "config_dir",
    "config_path",
    "data_config",
    "method",
    "voxelize_overrides",
]

Values: TypeAlias = dict[str, Any]
"""Config values by dotted key, Python objects (``{"data.init_args.batch_size": 8, "trainer.max_steps": 100,
"trainer.check_val_every_n_epoch": None}``): what :func:`lcreg.cli.instantiate` applies after the config files, in
order, each merged like one more ``--config``. Producers return them and callers merge them as dicts
(``{**a, **b}``: a later key wins; a key set twice keeps its first position)."""

REFINE_CONFIG = "refine/icp.yaml"
"""ICP refinement after any method's estimate (test time)."""
VOXELIZE_CONFIG = "voxelize/lk27.yaml"
"""Voxelised IC-LK with 27 voxels for the LK models (test time)."""
_VOXELIZE_KEY = "model.init_args.voxel_grid"  # where VOXELIZE_CONFIG puts the grid, for values of its settings
LC_CONFIG = "lc.yaml"
"""Local consistency appended to any model's loss terms."""
SELF_MOTION_CONFIG = "self_motion.yaml"
"""The label-free self-motion term appended to any model's loss terms (the recipe of ``dvds_selfsup``)."""
MODELNET40 = "data/modelnet40.yaml"
DCP_PROTOCOL = "data/dcp_protocol.yaml"

DATA_CONFIGS: dict[str, str] = {
    "sevenscenes": "data/sevenscenes.yaml",
    "kitti": "data/kitti.yaml",
    "scanobjectnn": "data/scanobjectnn.yaml",
}
"""Data add-ons (they replace a model config's ModelNet40 data block)."""


@dataclass(frozen=True)
class MethodSpec:
    """How to build one benchmarked method.

    Attributes:
        label: Row label in tables.
        method: The library method it builds (a key of :data:`lcreg.methods.METHODS`).
        configs: Config files, relative to :func:`config_dir`, passed in order as ``--config``.
        learned: Whether the method has weights to train (a checkpoint is meaningful).
        refine: Optional refinement config appended after ``configs`` (``+ ICP`` rows).
        weights_from: Name of the method whose checkpoint this one reuses (``None``: its own).
        lc_variant: Name of the same host with local consistency (``LC + X``), if any.
        overrides: Values by dotted key (:data:`Values`) of the method itself (the original batch size), applied
            after ``configs``; a further config a caller adds wins over them where it sets the same key (see
            :func:`lcreg.experiments.benchmarking.building.method_layers`).
    """

    label: str
    method: str
    configs: tuple[str, ...]
    learned: bool
    refine: str | None = None
    weights_from: str | None = None
    lc_variant: str | None = None
    overrides: Mapping[str, Any] = field(default_factory=dict, hash=False)

    def config_files(self) -> tuple[str, ...]:
        """``configs`` followed by the refinement config (relative paths)."""
        return (*self.configs, self.refine) if self.refine else self.configs


def _batch(size: int) -> Values:
    return {"data.init_args.batch_size": size}


def _learned(model: str, batch: int | None = None) -> MethodSpec:
    """A learned method with its config on ModelNet40 (``batch``: the original batch size, else the data config's)."""
    info = LIBRARY[model]
    return MethodSpec(info.label, model, (info.config, MODELNET40), True, overrides=_batch(batch) if batch else {})


def _host(model: str, batch: int, lc: bool) -> MethodSpec:
    """A host of the LC + X table: ModelNet40 under the DCP-family protocol, with or without ``lc.yaml``."""
    info = LIBRARY[model]
    configs = (info.config, *((LC_CONFIG,) if lc else ()), MODELNET40, DCP_PROTOCOL)
    label = f"LC + {info.label}" if lc else info.label
    return MethodSpec(label, model, configs, True, lc_variant=None if lc else f"{model}_lc", overrides=_batch(batch))


def _ablation(stem: str, recipe: bool) -> tuple[str, MethodSpec]:
    """``ablation_<stem>`` (the paper's objective) or ``ablation_<stem>_selfsup`` (plus the self-motion term)."""
    label = f"DVDs ablation {stem}" + (" + self-motion" if recipe else "")
    configs = (f"ablation/{stem}.yaml", *((SELF_MOTION_CONFIG,) if recipe else ()))
    return f"ablation_{stem}" + ("_selfsup" if recipe else ""), MethodSpec(label, "dvds", configs, True)


ABLATION_CONFIGS = (
    "model_A",
    "model_B",
    "model_C",
    "model_D",
    "local_32",
    "local_96",
    "lambda_0.5_0.5",
    "lambda_1_0.1",
)
"""The distinct rows of the paper's ablation table (``configs/ablation/<stem>.yaml``; ``local_64`` and
``lambda_0.5_0.1`` are model D under another logger name, so they are not registered twice)."""


def _classical(label: str, model: str, config: str | None = None, refine: str | None = None) -> MethodSpec:
    """A classical row: ``model``'s config (or another config of the same class, e.g. point-to-plane ICP)."""
    return MethodSpec(label, model, (config or LIBRARY[model].config, MODELNET40), False, refine=refine)


# Batch sizes are the originals' (DCP 32, PRNet 36, IDAM 16, DeepGMR 32, PointNetLK 32, PCRNet 20, FMR-Net 8).
HOST_BATCHES = {"dcp": 32, "prnet": 36, "idam": 16, "deepgmr": 32}
"""The hosts of the LC + X table and their original batch sizes."""
METHODS: dict[str, MethodSpec] = {
    "dvds": MethodSpec("DVDs", "dvds", ("dvds_modelnet40.yaml",), True),
    "dvds_selfsup": MethodSpec("DVDs, self-motion recipe", "dvds", ("dvds_selfsup_modelnet40.yaml",), True),
    "dvds_voxel": MethodSpec("DVDs voxelised (27 voxels)", "dvds", ("dvds_modelnet40.yaml", VOXELIZE_CONFIG), True),
    "dvds_icp": MethodSpec(
        "DVDs + ICP", "dvds", ("dvds_modelnet40.yaml",), True, refine=REFINE_CONFIG, weights_from="dvds"
    ),
    "pointnetlk": _learned("pointnetlk", 32),
    "pcrnet": _learned("pcrnet", 20),
    "fmr": _learned("fmr", 8),
    **{host: _host(host, batch, lc=False) for host, batch in HOST_BATCHES.items()},
    **{f"{host}_lc": _host(host, batch, lc=True) for host, batch in HOST_BATCHES.items()},
    "icp": _classical("ICP point-to-point", "icp"),
    "icp_plane": _classical("ICP point-to-plane", "icp", config="models/icp_plane.yaml"),
    "ransac": _classical("FPFH + RANSAC", "ransac"),
    "fgr": _classical("FPFH + FGR", "fgr"),
    "ransac_icp": _classical("FPFH + RANSAC + ICP", "ransac", refine=REFINE_CONFIG),
    "fgr_icp": _classical("FPFH + FGR + ICP", "fgr", refine=REFINE_CONFIG),
    **dict(_ablation(stem, recipe) for recipe in (False, True) for stem in ABLATION_CONFIGS),
    "ransac_icp_sevenscenes": MethodSpec(
        "FPFH + RANSAC + ICP",
        "ransac",
        ("pipelines/ransac_icp_sevenscenes.yaml", DATA_CONFIGS["sevenscenes"]),
        False,
    ),
    "ransac_icp_kitti": MethodSpec(
        "FPFH + RANSAC + ICP", "ransac", ("pipelines/ransac_icp_kitti.yaml", DATA_CONFIGS["kitti"]), False
    ),
}
# A library method without a row of its own gets one: its config on ModelNet40 (a new method needs no edit here).
METHODS.update(
    {
        name: _learned(name) if info.learned else _classical(info.label, name)
        for name, info in LIBRARY.items()
        if name not in METHODS
    }
)
"""Every benchmarked row by name (each on a library method of :data:`lcreg.methods.METHODS`)."""


def method(name: str) -> MethodSpec:
    """The spec of ``name``.

    Raises:
        KeyError: If ``name`` is not in :data:`METHODS` (the message lists the known names).
    """
    try:
        return METHODS[name]
    except KeyError:
        raise KeyError(f"unknown method {name!r}; known: {', '.join(METHODS)}") from None


def config_dir() -> Path:
    """Lcreg's configs folder (:func:`lcreg.config.configs_root`: package data, or ``configs/`` of a checkout).

    Raises:
        lcreg.config.ConfigFileError: If lcreg's configs are missing (a broken install).
    """
    return configs_root()


def config_path(name: str | Path) -> Path:
    """``name`` resolved against :func:`config_dir` (absolute paths are kept).

    Raises:
        FileNotFoundError: If the file does not exist.
    """
    path = Path(name) if Path(name).is_absolute() else config_dir() / name
    if not path.is_file():
        raise FileNotFoundError(f"config {str(path)!r} does not exist")
    return path


def data_config(dataset: str) -> str:
    """The data add-on config of ``dataset`` (relative path).

    Raises:
        KeyError: If ``dataset`` is not in :data:`DATA_CONFIGS`.
    """
    if dataset not in DATA_CONFIGS:
        raise KeyError(f"unknown dataset {dataset!r}; known: {', '.join(DATA_CONFIGS)}")
    return DATA_CONFIGS[dataset]


def cli_args(section: str, values: Mapping[str, Any]) -> Values:
    """Constructor arguments of a config section as :data:`Values`: ``{"<section>.init_args.<name>": value}``.

    Args:
        section: ``"model"``, ``"data"`` or another class-valued key (``"model.init_args.voxel_grid"``).
        values: Constructor arguments (Python objects); ``None`` means "keep the config's value" and is skipped (set a
            ``None`` with the dotted key itself: ``{"data.init_args.num_points": None}``). A string is typed by the
            parser as command-line text is (``"5"`` for an int).

    Returns:
        Values for :func:`lcreg.experiments.benchmarking.build` and :func:`~lcreg.experiments.benchmarking.fit`.
    """
    return {f"{section}.init_args.{key}": value for key, value in values.items() if value is not None}


def voxelize_overrides(**values: Any) -> Values:
    """Values of :data:`VOXELIZE_CONFIG`'s settings (``normalize``, ``coarse_iterations``, ...)."""
    return cli_args(_VOXELIZE_KEY, values)
