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

``--init-args name=value`` (YAML values) replaces constructor arguments, for inference settings chosen after training
(``eval_iterations=20``). The source may also be an exported weights file (any suffix but ``.ckpt``): it is
re-exported with its class, tensors and metadata, plus ``source_weights`` and the new export time, e.g. to ship a
run's kept weights under a registered name or to change an inference setting of a shipped file.

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
from pathlib import Path
from typing import Any

import torch

from lcreg.checkpoints import CheckpointError, one_line
from lcreg.weights import (
    MAX_FILE_BYTES,
    REGISTRY,
    Metadata,
    PretrainedError,
    PretrainedFormatError,
    PretrainedSizeError,
    model_payload,
    slim_payload,
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
    "parse_init_args",
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


def _split(items: Sequence[str], option: str) -> list[tuple[str, str]]:
    """``["a=1", "b=x=y"]`` as ``[("a", "1"), ("b", "x=y")]``.

    Raises:
        ValueError: If an item has no ``=`` or an empty key (the message names ``option``).
    """
    pairs = []
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{option} expects key=value, got {item!r}")
        pairs.append((key.strip(), value))
    return pairs


def parse_metadata(items: Sequence[str]) -> Metadata:
    """``["steps=300", "machine=A100"]`` as ``{"steps": 300, "machine": "A100"}`` (ints and floats as numbers).

    Raises:
        ValueError: If an item has no ``=`` or an empty key.
    """
    return {key: _number_or_text(value) for key, value in _split(items, "--metadata")}


def parse_init_args(items: Sequence[str]) -> dict[str, Any]:
    """``["eval_iterations=20", "unit_scale=null"]`` as ``{"eval_iterations": 20, "unit_scale": None}`` (YAML values).

    Raises:
        ValueError: If an item has no ``=``, an empty key, or a value that is not YAML.
    """
    import yaml

    out: dict[str, Any] = {}
    for key, value in _split(items, "--init-args"):
        try:
            out[key] = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise ValueError(f"--init-args {key}: {value!r} is not a YAML value") from err
    return out


def _number_or_text(value: str) -> int | float | str:
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


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
    init_args: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``<out>/<name>.pt`` from a Lightning checkpoint or a weights file (see :func:`slim_payload`).

    Args:
        checkpoint: The Lightning checkpoint (``.ckpt``), or an exported weights file to re-export.
        name: The weights' name (registered names: :data:`~lcreg.weights.REGISTRY`).
        out: The folder to write to (created if needed); ``src/lcreg/weights/`` ships the file.
        metadata: Provenance entries (``command``, ``machine``, ``wall_time``, ...).
        class_path: The model class when the checkpoint does not name it.
        overwrite: Replace an existing ``<name>.pt``.
        card: Also write the model-card skeleton, or refresh its export block (:func:`write_card`).
        init_args: Constructor arguments replacing the source's (inference settings such as ``eval_iterations``).

    Returns:
        The path written.

    Raises:
        FileExistsError: ``<name>.pt`` exists and ``overwrite`` is false.
        PretrainedSizeError: The file would exceed :data:`~lcreg.weights.MAX_FILE_BYTES` (nothing is written).
        CheckpointError, PretrainedError, ValueError: See :func:`slim_payload`.
    """
    path = Path(out) / f"{name}.pt"
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
    payload = slim_payload(checkpoint, name, metadata, class_path, init_args)
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
    parser.add_argument(
        "checkpoint", type=Path, help="Lightning checkpoint (.ckpt, e.g. of `lcreg fit`) or a weights file to re-export"
    )
    parser.add_argument("--name", required=True, help=f"weights name, e.g. {', '.join(REGISTRY)}")
    parser.add_argument("--out", required=True, type=Path, help="folder to write <name>.pt to (src/lcreg/weights/)")
    parser.add_argument(
        "--metadata", nargs="+", action="extend", default=[], metavar="KEY=VALUE", help="provenance entries"
    )
    parser.add_argument(
        "--init-args",
        nargs="+",
        action="extend",
        default=[],
        metavar="NAME=VALUE",
        help="constructor arguments replacing the source's (YAML values), e.g. eval_iterations=20",
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
            parse_init_args(args.init_args),
        )
    except (CheckpointError, PretrainedError, FileExistsError, ValueError) as err:
        raise SystemExit(f"lcreg.weights.export: error: {err}") from err
    print(f"wrote {path} ({path.stat().st_size} bytes)")
    return path


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1:])
