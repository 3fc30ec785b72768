"""The training order: shuffled by ``(seed, epoch)``, with per-pair seeds, resumable in the middle of an epoch.

:class:`EpochSampler` replaces ``DataLoader(shuffle=True)`` for training. Epoch ``e``'s order and the seed of every
pair in it come from ``numpy.random.default_rng([seed, e])``, never from the global RNG, so the data stream does not
depend on what else draws random numbers (the model, the loaders' worker seeds, Lightning's prefetching) and a
resumed run sees exactly the batches an uninterrupted run would have seen.

The DataModules checkpoint the position with :func:`resume_position` (``LightningDataModule.state_dict``): the
epoch and the number of pairs the training loop has consumed; on resume the sampler skips them.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

__all__ = ["EpochSampler", "ResumableLoader", "ResumableTrainingOrder", "resume_position"]

_SEED_HIGH = 2**62


class EpochSampler(Sampler[Any]):
    """Indices of a dataset in an order fixed by ``(seed, epoch)``, optionally paired with a per-item seed.

    Args:
        size: Dataset length.
        seed: Base seed (``None``: drawn from the global torch RNG, which ``seed_everything`` fixes).
        pair_seeds: Yield ``(index, seed)`` (datasets that make a random pair per item, such as
            :class:`~lcreg.data.datamodule.PairDataset`) instead of plain indices.

    Example:
        >>> sampler = EpochSampler(4, seed=0, pair_seeds=False)
        >>> first = list(sampler); sampler.set_epoch(1)
        >>> sorted(first) == sorted(sampler) == [0, 1, 2, 3]
        True
    """

    def __init__(self, size: int, seed: int | None = None, pair_seeds: bool = True) -> None:
        if size < 0:
            raise ValueError(f"`size` must be >= 0, got {size}")
        self.size = size
        self.seed = int(torch.randint(0, _SEED_HIGH, (1,)).item()) if seed is None else int(seed)
        self.pair_seeds = pair_seeds
        self.epoch = 0
        self._start = 0

    def set_epoch(self, epoch: int) -> None:
        """The epoch of the next iteration (Lightning calls this before every training epoch)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return self.size

    def __iter__(self) -> Iterator[Any]:
        """The epoch's items, after the ones a resumed run already consumed (read at the first item)."""
        start, self._start = self._start, 0
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(self.size)
        seeds = rng.integers(0, _SEED_HIGH, size=self.size)
        for index in order[start:].tolist():
            yield (index, int(seeds[index])) if self.pair_seeds else index

    def state_dict(self) -> dict[str, int]:
        """The base seed, the epoch and the number of items to skip at its next iteration."""
        return {"seed": self.seed, "epoch": self.epoch, "start": self._start}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Continue from a :func:`resume_position`: that epoch, after the items already consumed."""
        self.seed, self.epoch, self._start = int(state["seed"]), int(state["epoch"]), int(state["start"])


def resume_position(trainer: Any, sampler: EpochSampler, batch_size: int) -> dict[str, int]:
    """Where training stands in the sampler's stream (the :class:`EpochSampler` state a resumed run loads).

    Counts the batches the training loop has started in this epoch (not the ones Lightning has prefetched); a
    finished epoch resumes at the start of the next one.

    Args:
        trainer: The running ``lightning.pytorch.Trainer``.
        sampler: The training loader's sampler.
        batch_size: Items per batch.
    """
    done = int(trainer.fit_loop.epoch_loop.batch_progress.current.ready)
    epoch = int(trainer.current_epoch)
    if done >= trainer.num_training_batches:
        return {"seed": sampler.seed, "epoch": epoch + 1, "start": 0}
    return {"seed": sampler.seed, "epoch": epoch, "start": done * batch_size}


class ResumableLoader(DataLoader[Any]):
    """A training DataLoader that Lightning treats as resumable mid-epoch (no "not resumable" warning).

    Its position lives in the DataModule's ``state_dict`` (:class:`ResumableTrainingOrder`), which Lightning restores
    on every resume, also at an epoch boundary where it skips loader states; these methods keep nothing.
    """

    def state_dict(self) -> dict[str, Any]:
        """Nothing: the DataModule checkpoints the sampler's position."""
        return {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Nothing to restore here (see the class docstring)."""


class ResumableTrainingOrder:
    """DataModule mixin: the training loader's :class:`EpochSampler`, its position saved in checkpoints.

    ``LightningDataModule.state_dict``/``load_state_dict`` are the hooks Lightning calls when it saves and restores
    a checkpoint (restored before the loaders are built); the position is applied to the next training sampler.
    """

    trainer: Any
    batch_size: int
    _train_sampler: EpochSampler | None = None
    _resume_state: dict[str, int] | None = None

    def training_sampler(self, size: int, pair_seeds: bool) -> EpochSampler:
        """A new training sampler over ``size`` items, continuing a restored checkpoint's position if any."""
        sampler = self._train_sampler = EpochSampler(size, pair_seeds=pair_seeds)
        if self._resume_state is not None:
            sampler.load_state_dict(self._resume_state)
            self._resume_state = None
        return sampler

    def state_dict(self) -> dict[str, Any]:
        """The training stream's position (:func:`resume_position`), saved in checkpoints."""
        if self._train_sampler is None or self.trainer is None:
            return {}
        return {"train_sampler": resume_position(self.trainer, self._train_sampler, self.batch_size)}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Continue the training stream of a checkpoint (applied when the training loader is built)."""
        self._resume_state = state_dict.get("train_sampler")
