"""The LightningDataModule: shards -> ``BatchedExample`` streams for fit / validate / test (docs/data.md).

Plain constructor arguments, so LightningCLI builds it from YAML. Rank and world size come from the trainer in
``setup`` (or ``set_distributed`` in tests), never from environment variables. The training DataLoader writes
the trainer's global step to shared memory each time an epoch starts, where every worker's stream reads it
(``stream.TrainStream``: a step inside an epoch resumes that epoch exactly); ``set_global_step`` does the
same by hand. ``state_dict`` / ``load_state_dict`` carry the step (and seed) through checkpoints.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader

from ..errors import MissingFileError
from .curriculum import GapCurriculum
from .stream import EvalStream, StreamConfig, TrainStream, counter_totals, new_counters

log = logging.getLogger("aesplat.data")
# Lightning warns that an IterableDataset's __len__ may be wrong with several workers; ours is exact by
# construction (each worker yields its fixed share of the rank's batches).
warnings.filterwarnings("ignore", message=r".*Your `IterableDataset` has `__len__` defined.*")


class DataModule(L.LightningDataModule):
    """Context/target batches streamed from ``root/{train,validation,test}/*.tar`` (``data_prep/to_shards.py``).

    Validation (and with it the "best" checkpoint) uses the ``validation`` split; the ``test`` split only
    when the shards have no validation split, with a warning that checkpoint selection then sees the test
    scenes (``to_shards.py --val-scenes N`` makes one; see docs/validation.md).

    Args:
        root: shard folder holding ``train/``, ``validation/`` and ``test/`` (and ``manifest.json``).
        image_size: square side fed to the model (shard images of another size are resized; use a multiple
            of 14 for the ViT patch size).
        batch_size / eval_batch_size: samples per training / evaluation batch (per rank).
        num_workers: DataLoader worker processes per rank.
        num_context_views, num_target_views: views per training sample (evaluation uses every target of the
            evaluation index unless ``eval_num_target_views`` is set).
        gap_initial, gap_final, gap_warmup_steps: the view-gap curriculum (allowed context gap range in frames
            at step 0 and after the warm-up; paper: 25 -> 90).
        flip_augment: mirror half of the training samples, cameras included.
        train_batches_per_epoch: batches every rank yields per training epoch (the stream itself is infinite).
        shuffle_buffer: samples held per worker for shuffling.
        seed: base seed of the training streams.
    """

    def __init__(
        self,
        root: str = "outputs/shards/synthetic",
        image_size: int = 224,
        batch_size: int = 10,
        num_workers: int = 4,
        num_context_views: int = 2,
        num_target_views: int = 1,
        gap_initial: tuple[int, int] = (25, 25),
        gap_final: tuple[int, int] = (25, 90),
        gap_warmup_steps: int = 150_000,
        flip_augment: bool = True,
        train_batches_per_epoch: int = 1000,
        eval_batch_size: int = 1,
        eval_num_target_views: int | None = None,
        shuffle_buffer: int = 64,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if image_size < 1 or batch_size < 1 or eval_batch_size < 1 or num_workers < 0:
            raise ValueError("image_size, batch_size and eval_batch_size must be >= 1, num_workers >= 0")
        self.root = Path(root)
        self.image_size = image_size
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size
        self.num_workers = num_workers
        self.num_context_views = num_context_views
        self.num_target_views = num_target_views
        self.eval_num_target_views = eval_num_target_views
        self.curriculum = GapCurriculum(tuple(gap_initial), tuple(gap_final), gap_warmup_steps)
        self.flip_augment = flip_augment
        self.train_batches_per_epoch = train_batches_per_epoch
        self.shuffle_buffer = shuffle_buffer
        self.seed = seed
        self._step = torch.zeros(1, dtype=torch.int64).share_memory_()
        self._counters = {split: new_counters(num_workers) for split in ("train", "val", "test")}
        self._rank: int | None = None
        self._world_size: int | None = None

    # ------------------------------------------------------------------------------------------- distributed

    def set_distributed(self, rank: int, world_size: int) -> None:
        """Fix rank and world size explicitly (tests, custom launchers); else ``setup`` takes the trainer's."""
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is outside world size {world_size}")
        self._rank, self._world_size = rank, world_size

    def setup(self, stage: str | None = None) -> None:
        if self.trainer is not None and self._rank is None:
            self._rank, self._world_size = self.trainer.global_rank, self.trainer.world_size
            self.set_global_step(max(self.global_step, self.trainer.global_step))

    @property
    def rank(self) -> int:
        return 0 if self._rank is None else self._rank

    @property
    def world_size(self) -> int:
        return 1 if self._world_size is None else self._world_size

    # ------------------------------------------------------------------------------------------- curriculum

    def set_global_step(self, step: int) -> None:
        """Tell every (already running) worker the current global step, read when an epoch's stream starts."""
        self._step[0] = int(step)

    @property
    def global_step(self) -> int:
        return int(self._step[0])

    def allowed_gap(self) -> tuple[int, int]:
        """The context-gap range the curriculum allows now."""
        return self.curriculum.allowed(self.global_step)

    def state_dict(self) -> dict[str, Any]:
        return {"global_step": self.global_step, "seed": self.seed}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.set_global_step(int(state_dict["global_step"]))
        self.seed = int(state_dict.get("seed", self.seed))

    # ------------------------------------------------------------------------------------------- counters

    def data_errors(self) -> dict[str, int]:
        """Skipped-data counters summed over workers, e.g. ``{"train/corrupt_samples": 0, ...}`` (to log)."""
        out = {}
        for split, table in self._counters.items():
            out.update({f"{split}/{k}": v for k, v in counter_totals(table).items()})
        return out

    # ------------------------------------------------------------------------------------------- loaders

    def has_split(self, split: str) -> bool:
        """Whether the shards hold ``split`` (see :func:`has_split`)."""
        return has_split(self.root, split)

    def validation_split(self) -> str:
        """The split validation runs on: ``validation`` when the shards have one, else ``test`` (warned)."""
        if self.has_split("validation"):
            return "validation"
        if not getattr(self, "_warned_no_validation", False):
            self._warned_no_validation = True
            log.warning(
                "%s has no validation split: validating on the test split, so checkpoint selection sees the "
                "test scenes; make one with `data_prep/to_shards.py --val-scenes N` (docs/validation.md)",
                self.root,
            )
        return "test"

    def shards(self, split: str) -> list[str]:
        """Sorted shard paths of ``root/<split>`` (see :func:`find_shards`)."""
        found = find_shards(self.root, split)
        manifest = self.root / "manifest.json"
        size = json.loads(manifest.read_text()).get("config", {}).get("size") if manifest.exists() else None
        if size is not None and size != self.image_size:
            log.info("shards are %dpx, resizing to image_size=%d while loading", size, self.image_size)
        return found

    def _config(self, train: bool) -> StreamConfig:
        return StreamConfig(
            image_size=self.image_size,
            batch_size=self.batch_size if train else self.eval_batch_size,
            num_context_views=self.num_context_views,
            num_target_views=self.num_target_views if train else self.eval_num_target_views,
            flip_augment=self.flip_augment and train,
        )

    def _loader(self, dataset: torch.utils.data.IterableDataset, on_epoch_start=None) -> DataLoader:
        """Workers batch the samples themselves (``batch_size=None``); ``on_epoch_start`` runs in the main
        process each time an iteration begins."""
        workers = self.num_workers
        options = {"batch_size": None, "num_workers": workers, "persistent_workers": workers > 0}
        if on_epoch_start is None:
            return DataLoader(dataset, **options)
        return _EpochStartLoader(on_epoch_start, dataset, **options)

    def epoch_length(self) -> int:
        """Training batches per rank and epoch: ``train_batches_per_epoch``, or what the trainer's
        ``limit_train_batches`` leaves of it. The stream's epochs must be the trainer's, or a resume would
        replay the wrong batches."""
        limit = getattr(self.trainer, "limit_train_batches", None) if self.trainer is not None else None
        if isinstance(limit, int) and not isinstance(limit, bool):
            return max(1, min(self.train_batches_per_epoch, limit))
        if isinstance(limit, float) and 0.0 < limit < 1.0:
            return max(1, int(self.train_batches_per_epoch * limit))
        return self.train_batches_per_epoch

    def train_dataset(self) -> TrainStream:
        return TrainStream(self.shards("train"), self._config(True), self.rank, self.world_size,
                           self._counters["train"], self._step, self.curriculum, self.epoch_length(),
                           seed=self.seed, shuffle_buffer=self.shuffle_buffer)  # fmt: skip

    def eval_dataset(self, split: str = "test") -> EvalStream:
        """The evaluation stream of ``test``, or of ``val``: the validation split (``validation_split``)."""
        counters = self._counters["test" if split == "test" else "val"]
        folder = "test" if split == "test" else self.validation_split()
        return EvalStream(self.shards(folder), self._config(False), self.rank, self.world_size, counters)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_dataset(), on_epoch_start=self._sync_epoch_start)

    def _sync_epoch_start(self) -> None:
        """Hand the trainer's global step to the stream as an epoch's iteration starts: the stream takes the
        epoch's first step (or, on a resume, the step inside it) from there."""
        if self.trainer is not None:
            self.set_global_step(self.trainer.global_step)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.eval_dataset("val"))

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.eval_dataset("test"))


class _EpochStartLoader(DataLoader):
    """A DataLoader that calls ``on_epoch_start`` in the main process each time an iteration (an epoch)
    starts, before any worker begins the epoch's stream."""

    def __init__(self, on_epoch_start, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.on_epoch_start = on_epoch_start

    def __iter__(self):
        self.on_epoch_start()
        return super().__iter__()


def has_split(root: str | Path, split: str) -> bool:
    """Whether the shards under ``root`` hold ``split``: the manifest lists it, or (without one) its folder
    has tars."""
    path = Path(root) / "manifest.json"
    if path.exists():
        return split in json.loads(path.read_text()).get("splits", {})
    return any((Path(root) / split).glob("*.tar"))


def find_shards(root: str | Path, split: str) -> list[str]:
    """Sorted shard paths of ``root/<split>``: those the manifest lists if there is one (stale tars from an
    older conversion are ignored), else every ``*.tar``. A one-line error naming the fix if there are none."""
    root = Path(root)
    if not root.is_dir():
        raise MissingFileError(
            f"no shards in {root}: the folder does not exist; give the folder `python data_prep/to_shards.py "
            "--out` wrote, or create it with that command"
        )
    folder = root / split
    path = root / "manifest.json"
    manifest = json.loads(path.read_text()) if path.exists() else {}
    listed = manifest.get("splits", {}).get(split)
    if listed is not None:
        wanted = [folder / s["shard"] for s in listed["shards"]]
        found = sorted(str(p) for p in wanted if p.exists())
        if len(found) < len(wanted):
            log.warning("%d shards listed in %s are missing from %s", len(wanted) - len(found), path, folder)
    else:
        found = sorted(str(p) for p in folder.glob("*.tar"))
    if not found:
        raise MissingFileError(
            f"no shards in {folder}: create them with `python data_prep/to_shards.py --src SRC --out "
            f"{root}` (or `python data_prep/synthetic.py --out SRC` first for the synthetic set)"
        )
    return found
