"""Lightning data module over pairs of shapes.

Splits and pairing come from the data config (``configs/data/*.yaml``). One pair per batch: meshes differ in
size, so batching happens by gradient accumulation in the Trainer (docs/architecture.md §2).
"""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable, Mapping

import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Sampler

from shapecorr.data.augmentation import AugmentedPair, SampleKey
from shapecorr.data.datasets import PairDataset, PairSample, ShapeDataset
from shapecorr.data.operators import OperatorConfig
from shapecorr.data.operators import plain_container as _plain
from shapecorr.data.shape import Normalization
from shapecorr.data.validation import ValidationOptions
from shapecorr.errors import ConfigError

SPLITS = ("train", "val", "test")
_SHAPE_SELECTORS = {"split", "names", "index_range", "split_file"}
_PAIR_OPTIONS = {"pairs", "include_self", "pair_file", "max_pairs"}


def _first_item(batch: list[PairSample]) -> PairSample:
    """Collate for batch size 1: the pair itself (no stacking of differently sized meshes)."""
    return batch[0]


def _dataclass_from(cls, value):
    if value is None or isinstance(value, cls):
        return cls() if value is None else value
    value = _plain(value)
    allowed = {f.name for f in fields(cls)}
    unknown = set(value) - allowed
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} option(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    return cls(**value)


class ResumableShuffleSampler(Sampler[int]):
    """Shuffled indices whose order depends only on ``(seed, epoch)``, able to start mid-epoch.

    Lightning calls :meth:`set_epoch` before each epoch; :meth:`resume_at` makes the next iteration skip the
    first ``skip`` indices of an epoch's permutation, so a run resumed from a mid-epoch checkpoint sees exactly
    the pairs the uninterrupted run would have seen next. ``len`` stays the full epoch length. With
    ``keys=True`` it yields :class:`~shapecorr.data.augmentation.SampleKey` ``(epoch, position, index)`` instead
    of the index (for datasets whose items depend on the epoch and the step, e.g. augmented training pairs).
    """

    def __init__(self, n: int, seed: int = 0, keys: bool = False):
        self.n = int(n)
        self.seed = int(seed)
        self.keys = bool(keys)
        self.epoch = 0
        self._skip = 0

    def set_epoch(self, epoch: int) -> None:
        """Epoch of the next iteration (its permutation depends on ``(seed, epoch)``)."""
        self.epoch = int(epoch)

    def resume_at(self, epoch: int, skip: int) -> None:
        """Next iteration: epoch ``epoch``, starting after its first ``skip`` indices."""
        self.epoch, self._skip = int(epoch), max(0, int(skip))

    def permutation(self, epoch: int) -> list[int]:
        """The full index order of an epoch."""
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + int(epoch))
        return torch.randperm(self.n, generator=generator).tolist()

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        skip, self._skip = self._skip, 0
        order = self.permutation(self.epoch)[skip:]
        if self.keys:
            return iter(SampleKey(self.epoch, skip + k, i) for k, i in enumerate(order))
        return iter(order)


class KeyedDistributedSampler(DistributedSampler):
    """A rank's shard of the shuffled indices (Lightning's ``DistributedSampler`` order).

    Items are :class:`~shapecorr.data.augmentation.SampleKey` ``(epoch, position in the shard, index)``.

    Used for datasets whose items depend on the epoch and the step (augmented training pairs) under several
    ranks; being a ``DistributedSampler``, Lightning keeps it (and calls its ``set_epoch``) instead of replacing
    it. Resumption restarts the epoch, as for Lightning's own sampler.
    """

    def __iter__(self):
        return iter(SampleKey(self.epoch, k, int(i)) for k, i in enumerate(super().__iter__()))


def _resume_position(trainer) -> tuple[int, int]:
    """(epoch, batches already trained in it) of a trainer restored from a checkpoint ((0, 0) when fresh).

    Mid-epoch (``epoch_progress`` started but not processed) the epoch loop's ``batch_progress.processed``
    counts the batches whose optimization finished before the checkpoint was written.
    """
    if trainer is None:
        return 0, 0
    epochs = trainer.fit_loop.epoch_progress.current
    if epochs.started > epochs.processed:
        return epochs.processed, trainer.fit_loop.epoch_loop.batch_progress.current.processed
    return epochs.processed, 0


class ShapePairDataModule(pl.LightningDataModule):
    """Train / val / test pairs of a FAUST/SCAPE-style folder.

    Parameters
    ----------
    root
        Dataset folder (see :mod:`shapecorr.data.datasets`).
    splits
        Per split (``train``, ``val``, ``test``) a selector: ``{split: NAME}`` (reads ``splits/NAME.txt``),
        ``{index_range: [start, stop]}``, ``{split_file: PATH}`` or ``{names: [...]}``; ``{}`` = all shapes.
    pairs
        Per split the pairing options of :class:`PairDataset`: ``include_self``, ``pair_file``, ``max_pairs``.
    normalization
        :class:`Normalization` fields.
    operators
        :class:`~shapecorr.data.operators.OperatorConfig` options: ``laplacian`` (data-wide), ``request``
        (operators every shape gets), ``n_eig`` (its eigenpairs), ``params`` (this dataset's parameter defaults per
        operator); models add their ``required_operators`` (:meth:`with_operators`).
    cache_dir
        Shape-cache root (default ``$SHAPECORR_CACHE`` or ``~/.cache/shapecorr``).
    num_workers
        DataLoader worker processes.
    prepare_workers
        Processes computing missing cache entries before training (default: all CPUs).
    synthetic
        If given, ``preset`` (default | tiny | large) plus any options of
        :class:`shapecorr.data.synthetic.SyntheticConfig`: the folder ``root`` is generated on first use
        (the embedded default dataset).
    shuffle_seed
        Seed of the training-pair shuffling generator (reproducible epochs).
    validation
        :class:`~shapecorr.data.validation.ValidationOptions` fields (``data.validation.*``).
    reference_points
        At most this many ground-truth points per shape (evenly spaced entries of the ``.vts`` files; None: all),
        see :class:`~shapecorr.data.datasets.ShapeDataset`.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        splits: Mapping[str, Mapping] | None = None,
        pairs: Mapping[str, Mapping] | None = None,
        normalization: Mapping | Normalization | None = None,
        operators: Mapping | OperatorConfig | None = None,
        cache_dir: str | os.PathLike | None = None,
        num_workers: int = 0,
        prepare_workers: int | None = None,
        synthetic: Mapping | None = None,
        shuffle_seed: int = 0,
        validation: Mapping | None = None,
        reference_points: int | None = None,
    ):
        super().__init__()
        self.root = Path(os.path.expanduser(str(root)))
        self.split_selectors = {s: dict(_plain(v) or {}) for s, v in (_plain(splits) or {}).items()}
        self.pair_options = {s: dict(_plain(v) or {}) for s, v in (_plain(pairs) or {}).items()}
        for group, allowed in ((self.split_selectors, _SHAPE_SELECTORS), (self.pair_options, _PAIR_OPTIONS)):
            for split, options in group.items():
                if split not in SPLITS:
                    raise ConfigError(f"unknown split {split!r}; use one of {SPLITS}")
                unknown = set(options) - allowed
                if unknown:
                    raise ConfigError(f"unknown option(s) {sorted(unknown)} for split {split!r}; "
                                      f"allowed: {sorted(allowed)}")
        self.normalization = _dataclass_from(Normalization, normalization)
        self.operators = OperatorConfig.from_options(operators)
        self.validation = _dataclass_from(ValidationOptions, validation)
        self.reference_points = reference_points
        self.cache_dir = cache_dir
        self.num_workers = num_workers
        self.prepare_workers = prepare_workers
        self.synthetic = _plain(synthetic)
        self.shuffle_seed = shuffle_seed
        self._shapes: dict[str, ShapeDataset] = {}
        self._pairs: dict[str, PairDataset] = {}
        self._train_wrapper: Callable[[PairDataset], Dataset] | None = None

    def augment_training(self, wrapper: Callable[[PairDataset], Dataset] | None) -> None:
        """Serve the training pairs through ``wrapper(pairs)`` (a model's data-side augmentation), or plainly (None).

        The wrapped dataset is indexed by :class:`~shapecorr.data.augmentation.SampleKey` ``(epoch, position,
        index)`` (:class:`ResumableShuffleSampler` with ``keys=True``; under several ranks
        :class:`KeyedDistributedSampler`, position = place in the rank's shard); it runs in the DataLoader workers.
        Call before the training loader is built (a model does it in its ``setup`` hook).
        """
        self._train_wrapper = wrapper

    def with_operators(self, request: Mapping[str, Mapping[str, Any]] | None = None, **changes: Any) -> None:
        """Add an operator request (e.g. a model's ``required_operators``) to the data; call before setup.

        Parameters
        ----------
        request
            ``{operator name: {param: value}}`` (:mod:`shapecorr.data.operators`), merged with the data's own by
            each operator's merge rule (the eigenbasis keeps the larger ``k``).
        **changes
            More requests by name (``with_operators(**model.required_operators)``), the data-wide setting
            ``laplacian``, or ``n_eig`` (a lower bound on the eigenbasis size).
        """
        self.operators = self.operators.with_request(request, **changes)
        self._shapes.clear()
        self._pairs.clear()

    def ensure_data(self) -> None:
        """Generate the synthetic folder if this module is configured with one and it is missing."""
        if self.synthetic is not None:
            from shapecorr.data.synthetic import ensure_synthetic_dataset, preset

            options = dict(self.synthetic)
            name = options.pop("preset", "default")
            # preset() rejects unknown option names with the list of valid ones
            ensure_synthetic_dataset(self.root, preset(name, **options))

    def shapes(self, split: str) -> ShapeDataset:
        """The :class:`ShapeDataset` of a split (built once)."""
        if split not in SPLITS:
            raise ConfigError(f"unknown split {split!r}; use one of {SPLITS}")
        if split not in self._shapes:
            self.ensure_data()
            self._shapes[split] = ShapeDataset(
                self.root,
                normalization=self.normalization,
                operators=self.operators,
                cache_dir=self.cache_dir,
                validation=self.validation,
                reference_points=self.reference_points,
                **self.split_selectors.get(split, {}),
            )
        return self._shapes[split]

    def pairs(self, split: str) -> PairDataset:
        """The :class:`PairDataset` of a split (built once)."""
        if split not in self._pairs:
            self._pairs[split] = PairDataset(self.shapes(split), **self.pair_options.get(split, {}))
        return self._pairs[split]

    # Lightning hooks -------------------------------------------------------------------------------------
    def prepare_data(self) -> None:
        """Rank 0 only: generate data if needed and fill the cache for every split in parallel."""
        self.ensure_data()
        done = set()
        for split in SPLITS:
            ds = self.shapes(split)
            key = tuple(ds.names)
            if key not in done:
                ds.prepare(num_workers=self.prepare_workers)
                done.add(key)

    def setup(self, stage: str | None = None) -> None:
        """Build the pair datasets of every split."""
        for split in SPLITS:
            self.pairs(split)

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        sampler, generator = None, None
        dataset = self.pairs(split)
        wrapped = split == "train" and self._train_wrapper is not None
        if wrapped:
            dataset = self._train_wrapper(dataset)
        if shuffle and (self.trainer is None or self.trainer.world_size == 1):
            # (seed, epoch)-determined order that can restart mid-epoch: resumed runs see the same pairs
            sampler = ResumableShuffleSampler(len(dataset), self.shuffle_seed, keys=wrapped)
            sampler.resume_at(*_resume_position(self.trainer))
        elif shuffle and wrapped:
            # several ranks, items keyed by the epoch: Lightning's shuffling, with keys
            sampler = KeyedDistributedSampler(dataset, num_replicas=self.trainer.world_size,
                                              rank=self.trainer.global_rank, shuffle=True, seed=self.shuffle_seed)
        elif shuffle:
            # several ranks: Lightning's DistributedSampler shuffles per (seed, epoch); resumption restarts the epoch
            generator = torch.Generator().manual_seed(self.shuffle_seed)
        return DataLoader(
            dataset,
            batch_size=1,
            shuffle=shuffle and sampler is None,
            sampler=sampler,
            generator=generator,
            num_workers=self.num_workers,
            collate_fn=_first_item,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        """Shuffled loader of the training pairs."""
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        """Loader of the validation pairs, in order."""
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        """Loader of the test pairs, in order."""
        return self._loader("test", shuffle=False)

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        """Move a batch to ``device``: pairs by their own ``to``, anything else as Lightning does."""
        if isinstance(batch, (PairSample, AugmentedPair)):
            return batch.to(device)
        return super().transfer_batch_to_device(batch, device, dataloader_idx)
