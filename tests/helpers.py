"""What the whole test suite shares: synthetic shards, a tiny checkpoint as `aesplat fit` lays it out, the
`aesplat` command run in this process, and what several suites check against."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
IMAGE_SIZE = 28
SH_DEGREE = 2
IN_CI = os.environ.get("CI", "").lower() in ("1", "true")

# Every character a file system allows in a name: a key survives conversion intact, or is refused by name.
ODD_KEYS = ["room one", "kitchen/2", "ünïcødé-日本", "x" * 300, "line\nbreak", 'a,b"c', "-leading", "..",
            "CASE", "case"]  # fmt: skip


def make_shards(
    root: Path, size: int = 28, frames: int = 12, height: int = 48, width: int = 64, **scenes
) -> Path:
    """Synthetic scenes (``generate_dataset(root / "src", ...)``; ``scenes``: its counts and seed) converted to
    ``size`` px shards in ``root / "shards"``, which it returns."""
    from aesplat.data import convert_dataset, generate_dataset

    generate_dataset(root / "src", frames=frames, height=height, width=width, **scenes)
    convert_dataset(root / "src", root / "shards", size=size, progress=False)
    return root / "shards"


def identity_views(v: int, size: int = IMAGE_SIZE):
    """A ``BatchedViews`` of one sample: ``v`` random square images, every camera at the origin looking down z
    (normalised intrinsics, focal 1)."""
    import torch

    from aesplat.types import BatchedViews

    return BatchedViews(
        images=torch.rand(1, v, 3, size, size),
        extrinsics=torch.eye(4).repeat(1, v, 1, 1),
        intrinsics=torch.tensor([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]).repeat(1, v, 1, 1),
        index=torch.arange(v)[None],
    )


def write_tar(path: Path, samples: list[tuple[str, dict[str, bytes]]]) -> None:
    """Write samples [(key, {ext: bytes})] as one shard (see :class:`aesplat.data.tar_files.ShardWriter`)."""
    from aesplat.data.tar_files import ShardWriter

    with ShardWriter(path) as writer:
        for key, sample in samples:
            writer.add(key, sample)
        writer.commit()


def sample_keys(batch) -> list[tuple[str, tuple[int, ...]]]:
    """(scene, frame ids) per element of a ``BatchedExample``: what identifies a sample."""
    import torch

    frames = torch.cat([batch.context.index, batch.target.index], dim=1).tolist()
    return [(s, tuple(f)) for s, f in zip(batch.scene, frames)]


def write_tiny_checkpoint(
    run_dir: Path, data_root: str = "unused", image_size: int = IMAGE_SIZE, cameras: str = "predicted", **net
) -> Path:
    """A random-init tiny model saved by a real Lightning Trainer, plus the run's config.yaml (as `aesplat fit`
    lays them out: RUN/checkpoints/last.ckpt, RUN/config.yaml). ``net``: more ``model.net`` settings."""
    from lightning.pytorch import Trainer

    from aesplat.train import AESplatModule, EvalConfig, LossConfig, NetConfig

    module = AESplatModule(
        net=NetConfig(size="tiny", sh_degree=SH_DEGREE, near=0.1, far=20.0, **net),
        loss=LossConfig(lpips_weight=0.0),
        eval=EvalConfig(metrics_lpips=False),
        cameras=cameras,
    )
    trainer = Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                      enable_model_summary=False, accelerator="cpu")  # fmt: skip
    trainer.strategy.connect(module)
    ckpt = run_dir / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    trainer.save_checkpoint(ckpt, weights_only=True)
    # data.near / far as runs wrote them before the depth range became the model's alone: still read
    data = {"root": data_root, "image_size": image_size, "near": 0.1, "far": 20.0, "eval_batch_size": 1}
    (run_dir / "config.yaml").write_text(yaml.safe_dump({"data": data}))
    return ckpt


def aesplat(capsys, *args: str) -> tuple[int, str]:
    """Run `aesplat ARGS` in this process; (exit status, stderr + the SystemExit message)."""
    from aesplat import cli

    with pytest.raises(SystemExit) as info:
        cli.main(list(args))
    code = info.value.code
    err = capsys.readouterr().err
    if isinstance(code, str):  # SystemExit("message"): Python prints it on stderr and exits with 1
        return 1, err + code + "\n"
    return code, err


def one_line(text: str, after_start: bool = False) -> str:
    """The only line of ``text`` (``after_start``: besides the thread policy's, printed when a run starts)."""
    lines = [line for line in text.splitlines() if line.strip()]
    if after_start:
        lines = [line for line in lines if not line.startswith("aesplat: torch CPU threads")]
    assert len(lines) == 1, text
    assert "Traceback" not in text
    return lines[0]


def common(shards: Path, run_dir: Path) -> list[str]:
    """`aesplat fit|test|validate` arguments of the smoke config on ``shards``, writing to ``run_dir``."""
    return ["-c", "conf/smoke.yaml", "--data.root", str(shards), "--trainer.default_root_dir", str(run_dir),
            "--trainer.logger", "false"]  # fmt: skip


def tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def need(available: bool, what: str) -> None:
    """Skip without ``what`` on a developer's machine; fail in CI, which installs it (Makefile, .ci/run)."""
    if not available:
        (pytest.fail if IN_CI else pytest.skip)(f"{what} is not installed")
