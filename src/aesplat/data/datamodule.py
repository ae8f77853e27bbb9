"""The LightningDataModule: shards -> ``BatchedExample`` streams for fit / validate / test (docs/data.md).

Plain constructor arguments, so LightningCLI builds it from YAML. Rank and world size come from the trainer in
``setup`` (or ``set_distributed`` in tests), never from environment variables. The training DataLoader writes
the trainer's global step into ``step_tracker`` each time an epoch starts, where every worker's stream reads
it (``stream.TrainStream``: a step inside an epoch resumes that epoch exactly); the training module writes it
after every step. ``state_dict`` / ``load_state_dict`` carry the step (and seed) through checkpoints.
"""

from __future__ import annotations

import functools
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.fabric.utilities.seed import pl_worker_init_function
from torch.utils.data import DataLoader

from ..errors import UserError, ignore_stop_signals_in_worker, stop_signals_blocked
from ..types import StepTracker
from .curriculum import GapCurriculum
from .decode import StreamConfig
from .manifest import SceneRef, SplitRecord, data_digest, partition, read_manifest, training_scenes
from .manifest import find_shards as find_listed_shards
from .manifest import has_split as split_listed
from .remote import DownloadSettings, FetchError, RemoteShards, is_url, manifest_folder
from .sampler import ContextCount, ViewSampler
from .stream import COUNTERS, EvalStream, TrainStream, new_counters

__all__ = ["DataModule", "find_shards", "has_split", "validation_split"]

TEST_SPLITS = ("test", "validation")

log = logging.getLogger("aesplat.data")
# The ranges of settings: setting -> (lowest value, what it must be, whether None passes); refused in one line
# when a DataModule is built, and by ``aesplat.config_checks`` before a command writes anything.
RANGES: dict[str, tuple[int, str, bool]] = {
    "image_size": (1, "a positive number of pixels", False),
    "batch_size": (1, "1 or more samples", False),
    "eval_batch_size": (1, "1 or more samples", False),
    "num_workers": (0, "0 or more worker processes", False),
    "eval_num_target_views": (1, "1 or more (or unset: every target)", True),
    "eval_transfer_scale": (1, "1 (off) or more", False),
}
# Lightning warns that an IterableDataset's __len__ may be wrong with several workers; ours is exact by
# construction (each worker yields its fixed share of the rank's batches).
warnings.filterwarnings("ignore", message=r".*Your `IterableDataset` has `__len__` defined.*")


class DataModule(L.LightningDataModule):
    """Context/target batches streamed from ``root/{train,validation,test}/*.tar`` (``data_prep/to_shards.py``).

    Training draws every example at run time from whole scenes (docs/data.md). Validation (and with it the
    "best" checkpoint) uses the ``validation`` split; shards without one are refused for validation unless
    ``validate_on_test`` asks for the test split by name (``to_shards.py --val-scenes N`` makes one; see
    docs/validation.md).

    Args:
        root: shard folder holding ``train/``, ``validation/`` and ``test/`` (and ``manifest.json``), or its
            http(s) URL: shards fetched into ``cache_dir`` as the streams read them (docs/data.md, "Data on a
            server"; credentials from the environment only).
        image_size: square side fed to the model (shard images of another size are resized; use a multiple
            of 14 for the ViT patch size).
        batch_size / eval_batch_size: samples per training / evaluation batch (per rank).
        num_workers: DataLoader worker processes per rank.
        num_context_views: context views per training example: a number, or a range [lo, hi] from which each
            batch draws its count (all its samples share it; deterministic from the seed and the step).
        num_target_views: target views per training example, drawn between the outer context views.
        gap_initial, gap_final, gap_warmup_steps: the view-gap curriculum (allowed context gap range in frames
            at step 0 and after the warm-up; paper: 25 -> 90).
        min_target_distance: frames a training target keeps from the outer context views, at least (>= 1).
        examples_per_scene: training examples drawn from each scene read, each with its own views, entering the
            shuffle buffer separately (fewer reads per example; more repetition within a buffer).
        fixed_pool: 0 draws every training example afresh; N > 0 draws N examples per scene once (seeded by
            ``seed`` and the scene) and reuses them, as pre-drawn samples would (for comparisons).
        flip_augment: mirror half of the training samples, cameras included.
        train_batches_per_epoch: batches every rank yields per training epoch (the stream itself is infinite).
        eval_num_target_views: targets per evaluation sample (None: every target of the evaluation index).
        eval_num_context_views: context views of evaluation samples (None: ``num_context_views``, or the lower
            end of its range); shards carry k-view contexts up to ``to_shards.py --eval-context-views``.
        validate_on_test: validate on the test split when the shards have no validation split (checkpoint
            selection then sees the test scenes; the logs say so at every validation).
        test_split: the split ``aesplat test`` scores: ``test``, or ``validation`` to compare settings on the
            scenes choices are made on (docs/validation.md).
        eval_transfer_scale: s > 1 also decodes every evaluation target at s x image_size, the ground truth of
            the resolution-transfer metric (``aesplat test``'s ``transfer_gain_db``); the shards must hold
            images at least that large (convert them with ``to_shards.py --size`` s x image_size).
        shuffle_buffer: examples held per worker for shuffling (each holds its scene's small members; frames are
            read from the shard when picked).
        seed: base seed of the training streams (and of the fixed pools).
        cache_dir: where shards fetched from a URL ``root`` are kept, verified, for later runs (None:
            ``$TMPDIR/aesplat-shards-<user id>``, or under /tmp): a folder of yours that only you can write
            (made 0700 when missing); nothing is evicted.
        download_retries: further tries of a download that failed in a way another try may mend (a cut
            connection, a timeout, HTTP 5xx or 429); a cut download resumes where it stopped.
        download_timeout: seconds to connect, and at most between two pieces of data, before a try fails; a
            try also fails after this many seconds plus as many again for each megabyte received.
        download_backoff: seconds before the first retry, doubling with each further one.
        allow_other_data: resume a checkpoint (``--ckpt_path``) on data whose manifest lists other shards than
            the data it was trained on (refused otherwise).
    """

    def __init__(
        self,
        root: str = "outputs/shards/synthetic",
        image_size: int = 224,
        batch_size: int = 10,
        num_workers: int = 4,
        num_context_views: int | tuple[int, int] = 2,
        num_target_views: int = 1,
        gap_initial: tuple[int, int] = (25, 25),
        gap_final: tuple[int, int] = (25, 90),
        gap_warmup_steps: int = 150_000,
        min_target_distance: int = 1,
        examples_per_scene: int = 1,
        fixed_pool: int = 0,
        flip_augment: bool = True,
        train_batches_per_epoch: int = 1000,
        eval_batch_size: int = 1,
        eval_num_target_views: int | None = None,
        eval_num_context_views: int | None = None,
        validate_on_test: bool = False,
        test_split: str = "test",
        eval_transfer_scale: int = 1,
        shuffle_buffer: int = 64,
        seed: int = 0,
        cache_dir: str | None = None,
        download_retries: int = 5,
        download_timeout: float = 60.0,
        download_backoff: float = 1.0,
        allow_other_data: bool = False,
    ) -> None:
        super().__init__()
        settings = {"image_size": image_size, "batch_size": batch_size, "eval_batch_size": eval_batch_size,
                    "num_workers": num_workers, "eval_num_target_views": eval_num_target_views,
                    "eval_transfer_scale": eval_transfer_scale}  # fmt: skip
        for name, (lowest, must, optional) in RANGES.items():
            value = settings[name]
            if not (value is None and optional) and not (isinstance(value, (int, float)) and value >= lowest):
                raise UserError(f"invalid configuration: data.{name} = {value!r}: it must be {must}")
        if num_target_views < 1 or min_target_distance < 1 or examples_per_scene < 1 or fixed_pool < 0:
            raise UserError("data: num_target_views, min_target_distance and examples_per_scene must be >= 1, "
                            "fixed_pool >= 0")  # fmt: skip
        try:
            self.context_views = ContextCount.parse(num_context_views)
            self.eval_context_views = ContextCount.parse(eval_num_context_views or self.context_views.lo).lo
            self.curriculum = GapCurriculum(tuple(gap_initial), tuple(gap_final), gap_warmup_steps)
        except ValueError as err:
            raise UserError(f"data: {err}") from None
        if fixed_pool and not self.context_views.fixed:
            raise UserError("data.fixed_pool draws its examples once, with one count of context views: give "
                            "data.num_context_views a number, not a range")  # fmt: skip
        if test_split not in TEST_SPLITS:
            raise UserError(f"data.test_split must be one of {', '.join(TEST_SPLITS)}, got {test_split!r}")
        self.test_split = test_split
        self.num_context_views = num_context_views  # as given: what the model checks its head against
        self.eval_transfer_scale = eval_transfer_scale
        self.remote = None
        if is_url(str(root)):
            settings = DownloadSettings(download_retries, download_timeout, download_backoff)
            self.remote = RemoteShards(str(root), cache_dir, settings)
        # A URL stays a string (the name messages give); its shards are read from a local cache.
        self.root: str | Path = self.remote.url if self.remote else Path(root)
        self._shard_folder: Path | None = None if self.remote else Path(root)
        self.image_size = image_size
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size
        self.num_workers = num_workers
        self.num_target_views = num_target_views
        self.eval_num_target_views = eval_num_target_views
        self.min_target_distance = min_target_distance
        self.examples_per_scene = examples_per_scene
        self.fixed_pool = fixed_pool
        self.flip_augment = flip_augment
        self.train_batches_per_epoch = train_batches_per_epoch
        self.validate_on_test = validate_on_test
        self.shuffle_buffer = shuffle_buffer
        self.seed = seed
        self.allow_other_data = allow_other_data
        self.data_sha256: str | None = None  # what the manifest lists (data_digest), once the ranks agreed
        self.step_tracker = StepTracker()
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
            self.step_tracker.set(max(self.step_tracker.get(), self.trainer.global_step))
            self._agree_on_data()

    def _agree_on_data(self) -> None:
        """Make every rank read one data set: for a URL, rank 0 fetches the manifest and hands its bytes to the
        others (a re-upload between two ranks' fetches cannot split them); for a folder, the ranks compare what
        their manifests list (each node may hold its own copy). Every rank then stops with the same line, or
        none does."""
        if self.remote is not None and self._shard_folder is None:
            sent: tuple[bytes | None, str | None] = (None, None)
            if self.rank == 0:
                try:
                    sent = (self.remote.fetch_manifest(), None)
                except UserError as err:
                    sent = (None, str(err))
            data, error = _broadcast(sent)
            if error is not None:
                raise FetchError(error)
            self._shard_folder = self.remote.open(data)
        try:
            manifest, error = read_manifest(self.shard_folder()), None
        except UserError as err:
            manifest, error = None, str(err)
        self.data_sha256 = None if manifest is None else data_digest(manifest)
        seen = _all_gather((self.data_sha256, error))
        for rank, (_, error) in enumerate(seen):
            if error is not None:
                raise UserError(error if len(seen) == 1 else f"rank {rank}: {error}")
        other = [rank for rank, (digest, _) in enumerate(seen) if digest != seen[0][0]]
        if other:
            raise UserError(
                f"ranks {', '.join(map(str, other))} read other data than rank 0: the manifest.json of "
                f"{self.root} lists other shards on their nodes; give every node the same copy of the shards"
            )

    @property
    def rank(self) -> int:
        return 0 if self._rank is None else self._rank

    @property
    def world_size(self) -> int:
        return 1 if self._world_size is None else self._world_size

    # ------------------------------------------------------------------------------------------- curriculum

    def state_dict(self) -> dict[str, Any]:
        return {"global_step": self.step_tracker.get(), "seed": self.seed, "data_sha256": self.data_sha256}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore the step and seed of a checkpoint; a training resumed on other data than the checkpoint's
        (another manifest digest, :func:`data_digest`) is refused unless ``allow_other_data``."""
        saved = state_dict.get("data_sha256")
        fitting = self.trainer is not None and self.trainer.state.fn == "fit"
        if fitting and saved and self.data_sha256 and saved != self.data_sha256 and not self.allow_other_data:
            raise UserError(
                f"the checkpoint was trained on other data than {self.root} holds now (its manifest lists "
                f"other shards: {self.data_sha256[:12]}…, the checkpoint's {saved[:12]}…): resume on the data "
                "it was trained on, or pass --data.allow_other_data true to go on with these"
            )
        self.step_tracker.set(int(state_dict["global_step"]))
        self.seed = int(state_dict.get("seed", self.seed))

    # ------------------------------------------------------------------------------------------- counters

    def data_errors(self) -> dict[str, int]:
        """Skipped-data counters summed over workers, e.g. ``{"train/corrupt_samples": 0, ...}`` (to log)."""
        return {f"{split}/{name}": int(total) for split, table in self._counters.items()
                for name, total in zip(COUNTERS, table.sum(0).tolist())}  # fmt: skip

    # ------------------------------------------------------------------------------------------- loaders

    def shard_folder(self) -> Path:
        """The folder the shards are read from: ``root``, or for a URL its cache, where this process fetches
        the manifest the first time it is asked."""
        if self._shard_folder is None:
            self._shard_folder = self.remote.open()
        return self._shard_folder

    def has_split(self, split: str) -> bool:
        """Whether the shards hold ``split`` (see :func:`has_split`)."""
        return split_listed(self.shard_folder(), split)

    def validation_split(self) -> str:
        """The split validation runs on (:func:`validation_split`); on the test split, every call logs it."""
        self.shard_folder()
        split = validation_split(self.root, self.validate_on_test)
        if split == "test":
            log.warning(
                "data.validate_on_test: validating on the TEST split of %s (it has no validation split): "
                "checkpoint selection sees the test scenes",
                self.root,
            )
        return split

    def _config(self, train: bool) -> StreamConfig:
        if not train:
            return StreamConfig(image_size=self.image_size, batch_size=self.eval_batch_size,
                                context_views=ContextCount(self.eval_context_views, self.eval_context_views),
                                num_target_views=self.eval_num_target_views,
                                large_scale=self.eval_transfer_scale)  # fmt: skip
        return StreamConfig(
            image_size=self.image_size,
            batch_size=self.batch_size,
            context_views=self.context_views,
            num_target_views=self.num_target_views,
            flip_augment=self.flip_augment,
            examples_per_scene=self.examples_per_scene,
        )

    def _loader(self, dataset: torch.utils.data.IterableDataset, on_epoch_start=None) -> DataLoader:
        """Workers batch the samples themselves (``batch_size=None``) and outlive a stop signal sent to the
        whole process group (:func:`start_worker`); ``on_epoch_start`` runs in the main process each time an
        iteration begins."""
        workers = self.num_workers
        options = {"batch_size": None, "num_workers": workers, "persistent_workers": workers > 0}
        if workers:
            options["worker_init_fn"] = functools.partial(start_worker, rank=self.rank)
        return _Loader(dataset, on_epoch_start=on_epoch_start, **options)

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
        """The training stream of this rank, after checking (one line each) that the shards hold whole scenes,
        that every rank gets scenes of its own and that some of them give examples all along the curriculum."""
        scenes = training_scenes(self.shard_folder(), fetched_later=self.remote is not None)
        mine = partition(sorted(scenes, key=lambda s: (s.shard, s.key)), self.rank, self.world_size)
        if not mine:
            raise UserError(
                f"{len(scenes)} training scenes in {self.root} cannot give each of {self.world_size} "
                "ranks a scene of its own: convert more scenes or train on fewer devices"
            )
        sampler = ViewSampler(self.num_target_views, self.min_target_distance, self.fixed_pool,
                              self.curriculum.span(), self.seed)  # fmt: skip
        self._check_usable(mine, sampler)
        return TrainStream(mine, self._config(True), sampler, self.rank, self.world_size,
                           self._counters["train"], self.step_tracker, self.curriculum, self.epoch_length(),
                           seed=self.seed, shuffle_buffer=self.shuffle_buffer, fetch=self._fetch())  # fmt: skip

    def _fetch(self):
        """What the streams call on a shard path before they open it: None for a folder, else the download of
        that shard into the cache (in the process that reads it: a DataLoader worker)."""
        return None if self.remote is None else self.remote.fetch

    def _check_usable(self, scenes: list[SceneRef], sampler: ViewSampler) -> None:
        """Refuse a run in which, at some step of the curriculum (checked at 17 points of the warm-up), none of
        this rank's scenes can give an example: it would stop later, in a worker, far from the cause."""
        steps = sorted({round(self.curriculum.warmup_steps * i / 16) for i in range(17)})
        lengths = sorted({s.frames for s in scenes})
        # Fresh examples depend on a scene's length only; a fixed pool on its key too.
        candidates = scenes if sampler.fixed_pool else [SceneRef("", "", n) for n in lengths]
        for count in range(self.context_views.lo, self.context_views.hi + 1):
            for step in steps:
                allowed = self.curriculum.allowed(step)
                if not any(sampler.unusable(s.frames, s.key, allowed, count) is None for s in candidates):
                    raise UserError(
                        f"no training scene in {self.root} gives an example at step {step}: a context gap in "
                        f"{list(allowed)} with {count} context and {self.num_target_views} target views "
                        f"(scenes have {lengths[0]}..{lengths[-1]} frames); change data.gap_initial/gap_final, "
                        "the view counts or data.min_target_distance, or convert longer scenes"
                    )

    def eval_dataset(self, split: str = "test") -> EvalStream:
        """The evaluation stream of ``test`` (the split ``test_split`` names), or of ``val``: the validation
        split (``validation_split``)."""
        counters = self._counters["test" if split == "test" else "val"]
        folder = self.test_split if split == "test" else self.validation_split()
        shards = find_listed_shards(self.shard_folder(), folder, fetched_later=self.remote is not None)
        manifest = read_manifest(self.shard_folder())
        if manifest is not None and manifest.size is not None and manifest.size != self.image_size:
            log.info("shards are %dpx, resizing to image_size=%d while loading", manifest.size, self.image_size)
        large = self.image_size * self.eval_transfer_scale
        if self.eval_transfer_scale > 1 and (
            manifest is None or manifest.size is None or manifest.size < large
        ):
            stored = "of unknown size" if manifest is None or manifest.size is None else f"{manifest.size}px"
            raise UserError(
                f"data.eval_transfer_scale {self.eval_transfer_scale} needs shards of at least {large}px as "
                f"ground truth; {self.root} holds images {stored}: convert with `python data_prep/to_shards.py "
                f"--src SRC --out DIR --size {large}` and give --data.root DIR"
            )
        record = None if manifest is None else manifest.splits.get(folder)
        k = self.eval_context_views
        if record is not None and k > record.context_views:
            raise UserError(
                f"the {folder} shards in {self.root} carry contexts of up to {record.context_views} "
                f"views, not {k}: convert again with `python data_prep/to_shards.py --src SRC --out "
                f"{self.root} --eval-context-views {k}`"
            )
        check_target_count(self.root, folder, self.eval_num_target_views, record)
        return EvalStream(shards, self._config(False), self.rank, self.world_size, counters, self._fetch())

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_dataset(), on_epoch_start=self._sync_epoch_start)

    def _sync_epoch_start(self) -> None:
        """Hand the trainer's global step to the stream as an epoch's iteration starts: the stream takes the
        epoch's first step (or, on a resume, the step inside it) from there."""
        if self.trainer is not None:
            self.step_tracker.set(self.trainer.global_step)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.eval_dataset("val"))

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.eval_dataset("test"))


def _broadcast(obj: Any) -> Any:
    """Rank 0's ``obj`` on every rank (``obj`` itself outside a process group)."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return obj
    box = [obj]
    torch.distributed.broadcast_object_list(box, src=0)
    return box[0]


def _all_gather(obj: Any) -> list[Any]:
    """Every rank's ``obj``, by rank (``[obj]`` outside a process group)."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return [obj]
    out: list[Any] = [None] * torch.distributed.get_world_size()
    torch.distributed.all_gather_object(out, obj)
    return out


def start_worker(worker_id: int, rank: int = 0) -> None:
    """Every DataLoader worker's ``worker_init_fn``: ignore the stop signals, so that a signal sent to the
    whole process group leaves the step under way to finish and save
    (:func:`aesplat.errors.ignore_stop_signals_in_worker`); then seed the worker as Lightning does after
    ``seed_everything(workers=True)`` (as ``aesplat fit`` calls it), which it does itself only for a
    DataLoader without a ``worker_init_fn``."""
    ignore_stop_signals_in_worker()
    if int(os.environ.get("PL_SEED_WORKERS", "0")):
        pl_worker_init_function(worker_id, rank)


class _Loader(DataLoader):
    """A DataLoader that starts its workers with the stop signals blocked (:func:`start_worker` then takes
    them there: no thread of a worker, not even one started before its ``worker_init_fn``, ever runs torch's
    SIGTERM handler), and calls ``on_epoch_start`` (if any) in the main process each time an iteration (an
    epoch) starts, before any worker begins the epoch's stream."""

    def __init__(self, *args, on_epoch_start=None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.on_epoch_start = on_epoch_start

    def __iter__(self):
        if self.on_epoch_start is not None:
            self.on_epoch_start()
        return super().__iter__()

    def _get_iterator(self):
        with stop_signals_blocked():  # the workers are started here
            return super()._get_iterator()


def check_target_count(root: str | Path, folder: str, want: int | None, record: SplitRecord | None = None):
    """Refuse ``data.eval_num_target_views`` ``want`` above what some sample of split ``folder`` carries (the
    manifest counts its samples' targets; ``record``: that split's record, when already read): those samples
    would be skipped, and the evaluation would cover other scenes than it says, or none."""
    if want is None:
        return
    if record is None:
        manifest = read_manifest(local_folder(root))
        record = None if manifest is None else manifest.splits.get(folder)
    counts = {} if record is None else record.target_counts
    short = sum(n for targets, n in counts.items() if targets < want)
    if short:
        raise UserError(
            f"data.eval_num_target_views {want}: {short} of the {sum(counts.values())} samples of the {folder} "
            f"shards in {root} carry fewer targets (from {min(counts)} to {max(counts)}); give at most "
            f"{min(counts)}, or leave it unset to evaluate every target"
        )


def local_folder(root: str | Path) -> Path:
    """The folder holding the manifest of ``root``: ``root``, or for a URL the folder this process fetched its
    manifest into (:func:`aesplat.data.remote.manifest_folder`)."""
    return manifest_folder(str(root)) if is_url(str(root)) else Path(root)


def find_shards(root: str | Path, split: str) -> list[str]:
    """The shard paths of ``root/<split>`` (:func:`aesplat.data.manifest.find_shards`); for a URL, those its
    manifest lists, in the folder its manifest was fetched into, fetched when read."""
    return find_listed_shards(local_folder(root), split, fetched_later=is_url(str(root)))


def has_split(root: str | Path, split: str) -> bool:
    """Whether the shards of ``root`` (a folder or a URL) hold ``split``
    (:func:`aesplat.data.manifest.has_split`)."""
    return split_listed(local_folder(root), split)


def validation_split(root: str | Path, validate_on_test: bool = False) -> str:
    """The split validation runs on: ``validation`` when the shards under ``root`` have one; ``test`` only
    when asked by name (``validate_on_test``); else a one-line error saying how to make a validation split."""
    if has_split(root, "validation"):
        return "validation"
    if validate_on_test:
        return "test"
    raise UserError(
        f"{root} has no validation split, and validating on the test split would let checkpoint selection see "
        f"the test scenes: make one with `python data_prep/to_shards.py --src SRC --out {root} --val-scenes N` "
        "(synthetic data: `data_prep/synthetic.py --val-scenes N`), or set --data.validate_on_test true to "
        "validate on the test split knowingly"
    )
