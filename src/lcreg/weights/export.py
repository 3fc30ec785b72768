r"""Export a Lightning checkpoint as a slim pretrained-weights file (and, if asked, its model-card skeleton).

::

    python -m lcreg.weights.export runs/lcreg/version_0/checkpoints/epoch012-rre1.234.ckpt \
        --name dvds-modelnet40 --out src/lcreg/weights/ \
        --metadata "command=lcreg fit --config configs/dvds_modelnet40.yaml" machine="1x A100" [--card]

The checkpoint is read weights-only (:func:`lcreg.checkpoints.read_checkpoint`). The model class comes from the
checkpoint's ``hyper_parameters["_class_path"]`` (written by ``lcreg fit``; ``--class-path`` otherwise) and is built
from the hyper-parameters with the class's ``inference_hparams`` (DVDs: ``lambda_recon=0``, ``lambda_normal=0``, so
decoder and normal head are not built). Only the tensors of that inference model are written, never the
``training_only_modules`` (loss terms, decoders, normal head) nor optimiser state; the file is loaded back into the
model before it is written, and refused over :data:`~lcreg.weights.MAX_FILE_BYTES`. Default ``metadata``: the source
checkpoint's file name, ``global_step``, ``epoch``, the data module's settings, the export time and versions;
``--metadata key=value`` adds or replaces entries (integers and floats are stored as numbers).

``--card`` writes the model-card skeleton ``<name>.md`` beside the file (the template of
``docs/model_card_template.md``, with what the export knows filled in); when the card exists only its block between
``<!-- lcreg-export-begin`` and ``<!-- lcreg-export-end -->`` (size, sha256, class, arguments, metadata) is refreshed,
the hand-written rest is kept.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import sys
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

import lcreg
from lcreg.checkpoints import CheckpointError, CheckpointFormatError, CheckpointMismatchError, one_line, read_checkpoint
from lcreg.weights import (
    FORMAT,
    MAX_FILE_BYTES,
    NAME_PATTERN,
    REGISTRY,
    PretrainedBuildError,
    PretrainedError,
    PretrainedFormatError,
    PretrainedSizeError,
    PretrainedWeights,
    class_path_of,
    is_plain_mapping,
    load_into,
    resolve_class,
    training_only,
    validated,
)

__all__ = [
    "CARD_BEGIN",
    "CARD_END",
    "CARD_HEADINGS",
    "card_block",
    "card_skeleton",
    "export_weights",
    "main",
    "model_payload",
    "parse_metadata",
    "save",
    "serialize",
    "slim_payload",
    "write_card",
]

CARD_BEGIN = "<!-- lcreg-export-begin: written by `python -m lcreg.weights.export --card`; edit outside this block -->"
CARD_END = "<!-- lcreg-export-end -->"
CARD_HEADINGS = ("Usage", "Training", "Validation figures", "Test figures", "File")
"""The ``##`` sections of every model card, in order (``docs/model_card_template.md`` has the same)."""
Metadata = dict[str, str | int | float | bool]


def parse_metadata(items: Sequence[str]) -> Metadata:
    """``["steps=300", "machine=A100"]`` as ``{"steps": 300, "machine": "A100"}`` (ints and floats as numbers).

    Raises:
        ValueError: If an item has no ``=`` or an empty key.
    """
    out: Metadata = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--metadata expects key=value, got {item!r}")
        out[key.strip()] = _number_or_text(value)
    return out


def _number_or_text(value: str) -> int | float | str:
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


def slim_payload(
    checkpoint: str | Path,
    name: str,
    metadata: Mapping[str, str | int | float | bool] | None = None,
    class_path: str | None = None,
) -> dict[str, Any]:
    """The content of the weights file for a Lightning checkpoint (nothing written).

    Args:
        checkpoint: A checkpoint of ``lcreg fit`` (any Lightning checkpoint with ``hyper_parameters``).
        name: The name stored in the file (:data:`~lcreg.weights.NAME_PATTERN`).
        metadata: Entries added to (or replacing) the default metadata.
        class_path: The model class when the checkpoint does not name it (``hyper_parameters["_class_path"]``).

    Returns:
        The dict :func:`torch.save` writes: ``format``, ``name``, ``class_path``, ``init_args``, ``state_dict``
        (inference tensors only, CPU, contiguous copies), ``lcreg_version``, ``metadata``.

    Raises:
        ValueError: A name outside :data:`~lcreg.weights.NAME_PATTERN`.
        CheckpointError: The checkpoint is missing, unreadable, has no hyper-parameters or class, or its tensors do
            not fit the class (:class:`~lcreg.checkpoints.CheckpointMismatchError`).
        PretrainedError: The class is not an lcreg ``RegistrationModule`` or refuses the hyper-parameters.
    """
    _check_name(name)
    content = read_checkpoint(checkpoint)
    hparams = content.get("hyper_parameters")
    if not isinstance(hparams, dict):
        raise CheckpointFormatError(checkpoint, "no 'hyper_parameters' (the model's constructor arguments)")
    class_path = class_path or hparams.get("_class_path")
    if not isinstance(class_path, str):
        raise CheckpointFormatError(checkpoint, "no model class in hyper_parameters['_class_path']; pass --class-path")
    meta = {**_default_metadata(checkpoint, content), **(metadata or {})}
    return _payload(class_path, hparams, content["state_dict"], name, meta, Path(checkpoint))


def model_payload(
    model: torch.nn.Module, name: str, metadata: Mapping[str, str | int | float | bool] | None = None
) -> dict[str, Any]:
    """The content of the weights file for a model in memory (its ``hparams`` and inference tensors; nothing written).

    Raises:
        ValueError: A name outside :data:`~lcreg.weights.NAME_PATTERN`.
        PretrainedError: The model is not an lcreg ``RegistrationModule``, or its tensors or hyper-parameters do not
            rebuild it.
    """
    _check_name(name)
    hparams = dict(getattr(model, "hparams", {}))
    meta = {**_time_metadata(), **(metadata or {})}
    return _payload(class_path_of(model), hparams, model.state_dict(), name, meta, Path(f"{name}.pt"))


def _check_name(name: str) -> None:
    if not NAME_PATTERN.fullmatch(name):
        raise ValueError(f"weights name {name!r} must match {NAME_PATTERN.pattern} (it becomes <name>.pt)")


def _payload(
    class_path: str,
    hparams: Mapping[str, Any],
    state: Mapping[str, torch.Tensor],
    name: str,
    metadata: Metadata,
    source: Path,
) -> dict[str, Any]:
    """Build the inference model of ``class_path`` from ``hparams``, take its tensors from ``state``, check it loads.

    Raises:
        CheckpointFormatError: Hyper-parameters that are not plain data.
        CheckpointMismatchError: ``state`` does not fit the class (see :func:`_inference_state`).
        PretrainedError: Not an lcreg ``RegistrationModule`` class, or it refuses the hyper-parameters.
    """
    cls = resolve_class(class_path, name)
    init_args = {k: v for k, v in hparams.items() if not k.startswith("_")}
    if not is_plain_mapping(init_args):
        raise CheckpointFormatError(source, "hyper_parameters hold values other than plain data")
    init_args.update(cls.inference_hparams)
    try:
        model = cls(**init_args)
    except (TypeError, ValueError) as err:
        raise PretrainedBuildError(name, f"{class_path} refuses the hyper-parameters: {err}") from err
    inference = _inference_state(model, state, source)
    payload = {
        "format": FORMAT,
        "name": name,
        "class_path": class_path,
        "init_args": init_args,
        "state_dict": inference,
        "lcreg_version": lcreg.__version__,
        "metadata": dict(metadata),
    }
    check = PretrainedWeights(name, source, name, class_path, init_args, inference, lcreg.__version__, {})
    load_into(model, check)  # the file loads back exactly as lcreg.pretrained will load it
    return payload


def _inference_state(
    model: torch.nn.Module, checkpoint_state: Mapping[str, torch.Tensor], checkpoint: str | Path
) -> dict[str, torch.Tensor]:
    """The checkpoint's tensors of ``model``'s inference modules (CPU, contiguous copies: no shared storage).

    Raises:
        CheckpointMismatchError: The checkpoint lacks an inference tensor, or holds tensors that are neither the
            model's nor training-only (another architecture).
    """
    wanted = [k for k in model.state_dict() if not training_only(model, k)]
    missing = [k for k in wanted if k not in checkpoint_state]
    foreign = [k for k in checkpoint_state if k not in wanted and not training_only(model, k)]
    if missing or foreign:
        raise CheckpointMismatchError(
            checkpoint,
            f"does not fit {type(model).__name__}: missing {missing[:5]} ({len(missing)}), "
            f"unexpected {foreign[:5]} ({len(foreign)})",
        )
    return {k: checkpoint_state[k].detach().to("cpu", copy=True).contiguous() for k in wanted}


def _time_metadata() -> Metadata:
    """The export time and torch version."""
    return {
        "exported_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "torch_version": str(torch.__version__),  # a str subclass torch.load(weights_only) refuses
    }


def _default_metadata(checkpoint: str | Path, content: Mapping[str, Any]) -> Metadata:
    """Provenance the checkpoint itself records (no absolute paths)."""
    meta: Metadata = {"source_checkpoint": Path(checkpoint).name, **_time_metadata()}
    for key in ("global_step", "epoch"):
        if isinstance(content.get(key), int):
            meta[key] = content[key]
    if isinstance(content.get("pytorch-lightning_version"), str):
        meta["lightning_version"] = content["pytorch-lightning_version"]
    data = content.get("datamodule_hyper_parameters")
    if isinstance(data, dict):
        meta["data"] = _data_summary(data)
    return meta


def _data_summary(hparams: Mapping[str, Any]) -> str:
    """``"ModelNet40DataModule(root=modelnet40_mini, num_points=1024, ...)"`` (folders by their last part)."""
    cls = str(hparams.get("_class_path", "data")).rpartition(".")[2]
    items = [
        f"{k}={Path(v).name if k == 'root' and isinstance(v, str) else v}"
        for k, v in hparams.items()
        if not k.startswith("_")
    ]
    return f"{cls}({', '.join(items)})"


def serialize(payload: Mapping[str, Any], name: str, limited: bool = True) -> bytes:
    """The bytes of ``torch.save(payload)``, checked to read back as :func:`lcreg.weights.read_weights` reads them.

    Args:
        payload: The file's content.
        name: The weights' name (for errors).
        limited: Refuse files over :data:`~lcreg.weights.MAX_FILE_BYTES` (the limit of shipped files).

    Raises:
        PretrainedSizeError: Over the limit, when ``limited`` (names the largest tensors).
        PretrainedFormatError: The bytes do not load weights-only as a valid weights file (a non-plain value).
    """
    buffer = io.BytesIO()
    torch.save(dict(payload), buffer)
    data = buffer.getvalue()
    try:
        content = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # an object that only full unpickling restores
        raise PretrainedFormatError(name, f"does not load weights-only: {one_line(str(err))}") from err
    validated(content, name, Path(f"{name}.pt"))
    if limited and len(data) > MAX_FILE_BYTES:
        state = payload["state_dict"]
        largest = sorted(state, key=lambda k: state[k].numel() * state[k].element_size(), reverse=True)[:3]
        sizes = ", ".join(f"{k} {state[k].numel() * state[k].element_size() / 1e6:.2f} MB" for k in largest)
        message = f"{len(data) / 1e6:.2f} MB exceeds the {MAX_FILE_BYTES / 1e6:g} MB limit (largest: {sizes})"
        raise PretrainedSizeError(name, message)
    return data


def export_weights(
    checkpoint: str | Path,
    name: str,
    out: str | Path,
    metadata: Mapping[str, str | int | float | bool] | None = None,
    class_path: str | None = None,
    overwrite: bool = False,
    card: bool = False,
) -> Path:
    """Write ``<out>/<name>.pt`` from a Lightning checkpoint (see :func:`slim_payload`); returns its path.

    Args:
        checkpoint: The Lightning checkpoint.
        name: The weights' name (registered names: :data:`~lcreg.weights.REGISTRY`).
        out: The folder to write to (created if needed); ``src/lcreg/weights/`` ships the file.
        metadata: Provenance entries (``command``, ``machine``, ``wall_time``, ...).
        class_path: The model class when the checkpoint does not name it.
        overwrite: Replace an existing ``<name>.pt``.
        card: Also write the model-card skeleton, or refresh its export block (:func:`write_card`).

    Raises:
        FileExistsError: ``<name>.pt`` exists and ``overwrite`` is false.
        PretrainedSizeError: The file would exceed :data:`~lcreg.weights.MAX_FILE_BYTES` (nothing is written).
        CheckpointError, PretrainedError, ValueError: See :func:`slim_payload`.
    """
    path = Path(out) / f"{name}.pt"
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
    payload = slim_payload(checkpoint, name, metadata, class_path)
    _write(path, serialize(payload, name))
    if card:
        write_card(path, payload)
    return path


def save(
    model: torch.nn.Module,
    path: str | Path,
    name: str | None = None,
    metadata: Mapping[str, str | int | float | bool] | None = None,
) -> Path:
    """Write a model in memory as a weights file (the one format, :mod:`lcreg.weights`); returns the path.

    Unlike :func:`export_weights` (files to ship), the size is not limited.

    Args:
        model: An lcreg ``RegistrationModule`` (its constructor arguments are its ``hparams``).
        path: The file to write (atomically: a partial file is renamed); ``lcreg.pretrained(path)`` reads it.
        name: The name stored in the file (default: the file's stem).
        metadata: Provenance entries.

    Raises:
        ValueError: A name outside :data:`~lcreg.weights.NAME_PATTERN`.
        PretrainedError: See :func:`model_payload` and :func:`serialize`.
    """
    path = Path(path)
    name = name or path.stem
    _write(path, serialize(model_payload(model, name, metadata), name, limited=False))
    return path


def _write(path: Path, data: bytes) -> None:
    """``data`` to ``path`` through a partial file (a crash never leaves a half-written weights file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_bytes(data)
    partial.replace(path)


# --- model card ----------------------------------------------------------------------------------------------------
def card_block(path: Path, payload: Mapping[str, Any]) -> str:
    """The export-owned block of a model card: file, size, sha256, class, arguments, version, metadata."""
    data = path.read_bytes()
    metadata = "; ".join(f"{k}={v}" for k, v in payload["metadata"].items())
    rows = [
        ("file", f"`{path.name}`"),
        ("file size", f"{len(data)} bytes ({len(data) / 1e6:.2f} MB)"),
        ("sha256", f"`{hashlib.sha256(data).hexdigest()}`"),
        ("class_path", f"`{payload['class_path']}`"),
        ("init_args", f"`{json.dumps(payload['init_args'], sort_keys=True)}`"),
        ("lcreg version", str(payload["lcreg_version"])),
        ("metadata", metadata.replace("|", "\\|")),
    ]
    table = "\n".join(f"| {field} | {value} |" for field, value in rows)
    return f"{CARD_BEGIN}\n| field | value |\n|---|---|\n{table}\n{CARD_END}"


def card_skeleton(path: Path, payload: Mapping[str, Any]) -> str:
    """A new model card: the sections of :data:`CARD_HEADINGS`, known facts filled in, ``TODO`` elsewhere."""
    name, meta = payload["name"], payload["metadata"]
    spec = REGISTRY.get(name)
    steps = f"{meta['global_step']} steps (epoch index {meta.get('epoch', '?')})" if "global_step" in meta else "TODO"

    def field(key: str, default: str = "TODO") -> str:
        return str(meta.get(key, default)).replace("|", "\\|")

    return f"""# {name}

{spec.description if spec else payload["class_path"]}. Model card: fill in every TODO by hand.

## Usage

```python
import lcreg

model = lcreg.pretrained("{name}")  # {payload["class_path"]}, eval mode, CPU; .to(device) to move it
result = model.register(points_src, points_ref)  # (B, N, 3), (B, M, 3) -> result.transform_ref_src (B, 4, 4)
```

`lcreg test --config <model config> --config <data config> --weights {name}` evaluates it; `lcreg fit ...
--weights {name}` fine-tunes from it.

## Training

| field | value |
|---|---|
| exact command | {field("command")} |
| data and split | {field("data")} |
| steps / epochs | {field("steps", steps)} |
| wall time | {field("wall_time")} |
| machine | {field("machine")} |

## Validation figures

TODO: the validation split the checkpoint was selected on (pairs, val/rre_mean_deg, recall), with the command.

## Test figures

TODO: the test split (pairs, RMSE(R) deg, MAE(R) deg, RMSE(t), recall), measured with this exact file, with the
command.

## File

{card_block(path, payload)}
"""


def write_card(path: Path, payload: Mapping[str, Any]) -> Path:
    """Write ``<name>.md`` beside the weights ``path``, or refresh the export block of an existing card.

    Raises:
        ValueError: An existing card without the export block (a hand-written card is never overwritten).
    """
    card = path.with_suffix(".md")
    if not card.exists():
        card.write_text(card_skeleton(path, payload), encoding="utf-8")
        return card
    text = card.read_text(encoding="utf-8")
    start, end = text.find(CARD_BEGIN), text.find(CARD_END)
    if start < 0 or end < start:
        raise ValueError(f"{card} has no export block ({CARD_BEGIN} ... {CARD_END}); not overwriting it")
    card.write_text(text[:start] + card_block(path, payload) + text[end + len(CARD_END) :], encoding="utf-8")
    return card


# --- command line --------------------------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m lcreg.weights.export",
        description="Export a Lightning checkpoint as a slim pretrained-weights file <out>/<name>.pt.",
    )
    parser.add_argument("checkpoint", type=Path, help="Lightning checkpoint (e.g. of `lcreg fit`)")
    parser.add_argument("--name", required=True, help=f"weights name, e.g. {', '.join(REGISTRY)}")
    parser.add_argument("--out", required=True, type=Path, help="folder to write <name>.pt to (src/lcreg/weights/)")
    parser.add_argument(
        "--metadata", nargs="+", action="extend", default=[], metavar="KEY=VALUE", help="provenance entries"
    )
    parser.add_argument("--class-path", help="model class when the checkpoint does not name it")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing <name>.pt")
    parser.add_argument("--card", action="store_true", help="write the model-card skeleton or refresh its block")
    return parser


def main(argv: Sequence[str] | None = None) -> Path:
    """Command-line entry point; errors exit with one line naming the file.

    Returns:
        The path written.
    """
    args = _parser().parse_args(argv)
    try:
        path = export_weights(
            args.checkpoint,
            args.name,
            args.out,
            parse_metadata(args.metadata),
            args.class_path,
            args.overwrite,
            args.card,
        )
    except (CheckpointError, PretrainedError, FileExistsError, ValueError) as err:
        raise SystemExit(f"lcreg.weights.export: error: {err}") from err
    print(f"wrote {path} ({path.stat().st_size} bytes)")
    return path


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1:])
