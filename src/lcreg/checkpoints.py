"""Reading ``torch.save`` files weights-only (Lightning checkpoints, exported weights), with typed errors.

Every file is read with ``torch.load(weights_only=True)``: tensors and plain containers only, no code runs. Needs
torch only. :mod:`lcreg.weights` (the one loader of weights files and checkpoints, their export) and the CLI's
``--ckpt_path`` check read through this module.

Errors: one family. :class:`CheckpointError` is the root of every error met reading weights or checkpoints (the
``lcreg.weights.Pretrained*Error`` classes derive from it and from the matching class here: a missing exported file
is a :class:`CheckpointNotFoundError` too), so ``except CheckpointError`` catches them all.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "CheckpointError",
    "CheckpointFormatError",
    "CheckpointMismatchError",
    "CheckpointNotFoundError",
    "CheckpointReadError",
    "check_class",
    "check_keys",
    "few_items",
    "first_non_finite",
    "load_submodule",
    "one_line",
    "read_checkpoint",
    "read_torch_file",
    "state_problems",
]


class CheckpointError(Exception):
    """A checkpoint or weights file could not be used; ``path`` names the file, ``reason`` says why.

    ``reason`` is the message without the file; ``path`` is ``None`` only for a weights name that names no file.
    """

    path: Path | None
    reason: str

    def __init__(self, path: str | Path, message: str) -> None:
        super().__init__(f"checkpoint {str(path)!r}: {message}")
        self.path = Path(path)
        self.reason = message


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """The checkpoint file does not exist."""


class CheckpointReadError(CheckpointError, ValueError):
    """The file is not a readable ``torch.save`` file of tensors and plain containers (empty, truncated, garbage)."""


class CheckpointFormatError(CheckpointError, ValueError):
    """The file loads but holds no ``state_dict`` (not a Lightning checkpoint)."""


class CheckpointMismatchError(CheckpointError, RuntimeError):
    """The ``state_dict`` does not fit the model (missing/unexpected keys or shapes: another architecture)."""


def read_torch_file(path: str | Path, map_location: str | torch.device = "cpu") -> Any:
    """The content of a ``torch.save`` file, read weights-only.

    Args:
        path: The file.
        map_location: Where tensors are loaded (default the CPU).

    Raises:
        CheckpointNotFoundError: ``path`` is not a file.
        CheckpointReadError: The file is empty or not a readable weights-only ``torch.save`` file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointNotFoundError(path, "no such file")
    if path.stat().st_size == 0:
        raise CheckpointReadError(path, "empty file")
    with path.open("rb") as fh:
        head = fh.read(8)
    if not head.startswith((b"PK", b"\x80")):  # torch.save writes a zip archive (or, legacy, a pickle)
        raise CheckpointReadError(path, f"not a torch.save file (a zip archive); it starts with {head!r}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # torch raises EOFError, UnpicklingError, RuntimeError, ... depending on the damage
        reason = f"not a readable weights-only torch file ({type(err).__name__}: {one_line(str(err))})"
        raise CheckpointReadError(path, reason) from err


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """A Lightning checkpoint (a dict with a ``state_dict`` dict), read weights-only.

    Raises:
        CheckpointNotFoundError: ``path`` is not a file.
        CheckpointReadError: The file cannot be read as a weights-only ``torch.save`` file.
        CheckpointFormatError: The content is not a dict with a ``state_dict``, or a tensor of it holds NaN/Inf.
    """
    content = read_torch_file(path, map_location)
    if not isinstance(content, dict) or not isinstance(content.get("state_dict"), dict):
        raise CheckpointFormatError(path, "no 'state_dict' (not a Lightning checkpoint)")
    bad = first_non_finite(content["state_dict"])
    if bad is not None:
        raise CheckpointFormatError(
            path, f"tensor `{bad[0]}` holds {bad[1]} NaN/Inf value(s): take an earlier checkpoint"
        )
    return content


def first_non_finite(state: Mapping[str, Any]) -> tuple[str, int] | None:
    """The first floating tensor of ``state`` holding NaN/Inf, with the count of such values (``None``: all finite)."""
    for key, value in state.items():
        if torch.is_tensor(value) and value.is_floating_point():
            bad = int((~torch.isfinite(value)).sum())
            if bad:
                return key, bad
    return None


def check_class(path: str | Path, checkpoint: dict[str, Any], class_path: str) -> None:
    """Refuse a checkpoint of another model class than ``class_path`` (``module.Class``).

    The class is the ``_class_path`` LightningCLI stores in ``hyper_parameters``; a checkpoint without it passes
    (its ``state_dict`` keys are checked when the model is built, :func:`check_keys`).

    Raises:
        CheckpointMismatchError: Naming both classes.
    """
    hparams = checkpoint.get("hyper_parameters")
    saved = hparams.get("_class_path") if isinstance(hparams, dict) else None
    if isinstance(saved, str) and saved != class_path:
        raise CheckpointMismatchError(path, f"holds a {saved} model, the config builds {class_path}")


def check_keys(path: str | Path, keys: Iterable[str], model: torch.nn.Module) -> None:
    """Refuse a ``state_dict`` whose keys differ from ``model``'s (another architecture or configuration).

    A key the model does not save but loads, a parameter left out of its ``state_dict()`` (a frozen LC metric, which
    its seed rebuilds: :class:`lcreg.nn.local_consistency.LocalConsistency`), is not unexpected: older checkpoints
    hold it.

    Raises:
        CheckpointMismatchError: Naming the model class and a few missing/unexpected keys.
    """
    saved, expected = set(keys), set(model.state_dict())
    loadable = expected | {name for name, _ in model.named_parameters()}
    missing, unexpected = sorted(expected - saved), sorted(saved - loadable)
    if not missing and not unexpected:
        return
    parts = [
        f"{label} {len(names)} keys ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''})"
        for label, names in (("lacks", missing), ("has unexpected", unexpected))
        if names
    ]
    raise CheckpointMismatchError(path, f"does not fit the configured {type(model).__name__}: {'; '.join(parts)}")


def one_line(text: str, limit: int = 300) -> str:
    """``text`` on one line, without terminal colour codes, at most ``limit`` characters (for error messages).

    torch's unpickling errors span many lines and colour their advice.
    """
    flat = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", text).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def state_problems(own: Mapping[str, Any], state: Mapping[str, Any], missing: list[str]) -> list[str]:
    """Why ``state`` does not load into a module whose state dict is ``own`` (empty: it loads).

    Tensors the module lacks, the ``missing`` ones (tensors of ``own`` that ``state`` must hold) and shapes.
    """
    problems = []
    if unexpected := [k for k in state if k not in own]:
        problems.append(f"tensors the model lacks: {few_items(unexpected)}")
    if missing:
        problems.append(f"inference tensors missing from the file: {few_items(missing)}")
    shapes = [
        f"{k} {tuple(v.shape)} vs {tuple(own[k].shape)}"
        for k, v in state.items()
        if k in own and v.shape != own[k].shape
    ]
    if shapes:
        problems.append(f"shapes (file vs model): {few_items(shapes)}")
    return problems


def few_items(items: list[str], limit: int = 5) -> str:
    """The first ``limit`` items, comma-separated, with a count of the rest."""
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


PACKAGE_WEIGHTS = Path(__file__).resolve().parent / "weights"
"""The folder of the shipped weights files (``lcreg.weights.weights_dir()``: ``<name>.pt``)."""


def load_submodule(model: torch.nn.Module, module: str, source: str | Path) -> Path:
    """Load one submodule of ``model`` (e.g. its ``encoder``) from the weights of any model that has the same one.

    Transfer learning across classes: e.g. PointNetLK starting from the PointNet of FMR-Net's reconstruction
    training (the PointNetLK original starts from a classifier's, ``--transfer-from``). Strict for that submodule:
    every one of its tensors must be in the file under ``<module>.`` with the same shape; the file's other tensors
    are ignored.

    Args:
        model: The model to load into (its other tensors are left as they are).
        module: The attribute name of the submodule (the prefix of its tensors in the file).
        source: A shipped weights name (``lcreg.pretrained_names()``), an exported ``.pt`` file or a Lightning
            checkpoint (``.ckpt``): both hold a ``state_dict``.

    Returns:
        The file read.

    Raises:
        CheckpointError: A subclass naming the file: missing, unreadable, without a ``state_dict`` or with NaN/Inf
            (as :func:`read_checkpoint`); :class:`CheckpointMismatchError` when ``model`` has no such submodule or
            the file's ``<module>.`` tensors do not fit it.
    """
    from lcreg.methods import pretrained_weights  # strings only

    path = (
        PACKAGE_WEIGHTS / f"{source}.pt" if isinstance(source, str) and source in pretrained_weights() else Path(source)
    )
    state = read_checkpoint(path)["state_dict"]
    target = getattr(model, module, None)
    if not isinstance(target, torch.nn.Module):
        raise CheckpointMismatchError(path, f"{type(model).__name__} has no submodule `{module}` to load")
    prefix = f"{module}."
    own = target.state_dict()
    sub = {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}
    if not sub:
        raise CheckpointMismatchError(path, f"holds no `{prefix}*` tensors to load into {type(model).__name__}")
    if problems := state_problems(own, sub, [k for k in own if k not in sub]):
        raise CheckpointMismatchError(
            path, f"its `{module}` does not fit that of {type(model).__name__}: {'; '.join(problems)}"
        )
    target.load_state_dict(sub)
    return path
