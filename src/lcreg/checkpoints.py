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
    "first_non_finite",
    "one_line",
    "read_checkpoint",
    "read_torch_file",
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
