"""Config files: where lcreg's own configs are, and how ``compose:`` lists expand.

The ``lcreg`` CLI and the experiments read configs through these functions.

lcreg's configs (``configs/`` of the repository: models, data, recipes, ablations) ship inside the package as
``lcreg/configs`` (package data of the wheel). A config path that starts with ``configs/`` and is not a file relative
to the working directory is looked up there, so ``lcreg fit --config configs/dvds.yaml`` works from a source checkout
and from an installed package alike (:func:`find_config`). :func:`configs_root` is that folder.

``--config`` may be given several times (later files override earlier ones), and a file may list the files it builds
on under ``compose:`` (paths relative to that file), which are read first, recursively (:func:`expand_configs`).
"""

from __future__ import annotations

import os
from pathlib import Path

import yaml

__all__ = [
    "CONFIGS_PREFIX",
    "ConfigFileError",
    "ConfigValueError",
    "UsageError",
    "configs_root",
    "expand_configs",
    "find_config",
]

CONFIGS_PREFIX = "configs"
"""First part of a config path that :func:`find_config` may take from the package's configs."""


class UsageError(Exception):
    """A mistake in the arguments or configs (exit code 2 from the command line)."""


class ConfigFileError(UsageError, FileNotFoundError):
    """A config file (or a file it composes) does not exist."""


class ConfigValueError(UsageError, ValueError):
    """A config is malformed (``compose`` cycle or value) or sets an unsupported option."""


def configs_root() -> Path:
    """The folder of lcreg's configs: ``lcreg/configs`` in an installed wheel, ``configs/`` of a source checkout.

    Raises:
        ConfigFileError: If neither exists (a broken install), naming both places.
    """
    package = Path(__file__).resolve().parent
    for folder in (package / CONFIGS_PREFIX, package.parents[1] / CONFIGS_PREFIX):
        if (folder / "dvds.yaml").is_file():
            return folder
    raise ConfigFileError(
        f"lcreg's configs are missing: neither {package / CONFIGS_PREFIX} (installed package) nor "
        f"{package.parents[1] / CONFIGS_PREFIX} (source checkout) holds them; reinstall lcreg"
    )


def find_config(path: str | Path) -> Path | None:
    """The config file ``path`` names: itself if it is a file, else a ``configs/...`` path in :func:`configs_root`.

    Args:
        path: A config path as given on the command line (relative to the working directory, or absolute).

    Returns:
        The file, or ``None`` if there is none (the caller reports it).
    """
    path = Path(path)
    if path.is_file():
        return path
    if path.is_absolute() or path.parts[:1] != (CONFIGS_PREFIX,):
        return None
    packaged = configs_root().joinpath(*path.parts[1:])
    return packaged if packaged.is_file() else None


def composed(path: Path, seen: tuple[Path, ...] = ()) -> list[Path]:
    """``path``'s ``compose:`` files (recursively, in order), then ``path`` itself (all resolved).

    Raises:
        ConfigFileError: If a composed file does not exist (names the file that lists it).
        ConfigValueError: On a ``compose`` cycle or a ``compose`` value that is not a list of paths.
    """
    path = path.resolve()
    if path in seen:
        raise ConfigValueError(f"config compose cycle: {' -> '.join(str(p) for p in (*seen, path))}")
    with path.open(encoding="utf-8") as fh:
        content = yaml.safe_load(fh)
    parts = content.get("compose") if isinstance(content, dict) else None
    if parts is None:
        return [path]
    if not isinstance(parts, list) or not all(isinstance(p, str) for p in parts):
        raise ConfigValueError(f"{path}: `compose` must be a list of config paths, got {parts!r}")
    files: list[Path] = []
    for part in parts:
        child = path.parent / part
        if not child.is_file():
            raise ConfigFileError(f"{path}: composed config {part!r} not found ({child})")
        files += composed(child, (*seen, path))
    return [*files, path]


def config_argument(arg: str, following: str | None) -> str | None:
    """The file named by ``--config=F`` or ``--config F`` (``None`` for other arguments)."""
    if arg.startswith("--config="):
        return arg.split("=", 1)[1]
    return following if arg == "--config" else None


def expand_configs(args: list[str]) -> list[str]:
    """Replace each ``--config F`` by ``--config`` of every file F composes, then F (found by :func:`find_config`).

    Args:
        args: Command-line arguments.

    Returns:
        The arguments with configs found and composed configs spelled out (other arguments unchanged, in order;
        a config that is not found is left for the parser to report), and ``--compose=null`` at the end when any
        file composed others, so the saved ``config.yaml`` (already complete) does not compose them again.
    """
    out: list[str] = []
    any_composed = False
    i = 0
    while i < len(args):
        path = config_argument(args[i], args[i + 1] if i + 1 < len(args) else None)
        step = 2 if args[i] == "--config" else 1
        file = None if path is None else find_config(path)
        if file is None:
            out += args[i : i + step] if path is not None else [args[i]]
            i += step if path is not None else 1
            continue
        files = composed(file)
        any_composed = any_composed or len(files) > 1
        for part in files:
            out += ["--config", str(part)]
        i += step
    return [*out, "--compose=null"] if any_composed else out


def config_texts(argv: list[str]) -> list[str]:
    """The arguments, then the text of every ``--config`` file they name that exists."""
    texts = list(argv)
    for i, arg in enumerate(argv):
        path = config_argument(arg, argv[i + 1] if i + 1 < len(argv) else None)
        if path and os.path.isfile(path):
            with open(path, encoding="utf-8") as fh:
                texts.append(fh.read())
    return texts
