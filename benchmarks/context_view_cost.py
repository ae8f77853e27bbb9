#!/usr/bin/env python
"""What each context view costs a training step: measured on this CPU, computed for the paper's network.

    python benchmarks/context_view_cost.py [--counts 2 3 4 5 6] [--sizes 42 224] [--steps 15] [--warmup 3]
        [--out docs/results/context_views]

1. Measured, on this machine: for every image side of --sizes and count of context views of --counts, one
   process of ``benchmarks/bench_train_step.py -c conf/demo.yaml --set model.net.view_aggregation=pool
   --set data.num_context_views=K --image-size SIDE --json FILE`` (the demo's tiny network, batch 2, one
   target view; real optimizer steps of ``aesplat fit``'s training step on synthetic shards): the median
   seconds per step after --warmup steps, and the peak resident memory of the process during the fit with
   how much it rose above the memory before the fit (the model, data module and imports). A process per
   point, so no point inherits another's memory.
2. Computed, for the paper's configuration (conf/re10k.yaml: the ``large`` network at 224², one target view,
   batch 1): the floating-point operations of one model forward per count, counted by torch's FLOP counter on
   the meta device (no weights, no data, no accelerator), split into the encoder, the geometry transformer's
   attention (its batched matrix products) and the rest of it, the heads and the appearance head, with the
   tokens and Gaussians of each count.

Writes under --out ``cost.json`` (every figure, with the date, commit, machine and load) and ``cost.md`` (one
table per part). A point already in ``cost.json`` under the same settings is kept: run it again to resume.
Heavy: run it under ``flock /work/heavy.lock`` where the machine is shared.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from unittest import mock

from common import provenance, write_whole

REPO = Path(__file__).resolve().parents[1]

CONFIG = "conf/demo.yaml"
PAPER_CONFIG = "conf/re10k.yaml"
PARTS = ("aggregator.patch_embed", "aggregator", "depth_head", "gaussian_head", "camera_head", "appearance")


# ----------------------------------------------------------------------------------------------- measured


def measure(size: int, count: int, steps: int, warmup: int) -> dict:
    """One ``bench_train_step.py`` process: a pool network trained with ``count`` context views at ``size``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "step.json"
        subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_train_step.py"), "-c", CONFIG, "--set",
                        "model.net.view_aggregation=pool", "--set", f"data.num_context_views={count}",
                        "--image-size", str(size), "--steps", str(steps), "--warmup", str(warmup), "--json",
                        str(out)], cwd=REPO, check=True, stdout=subprocess.DEVNULL)  # fmt: skip
        figures = json.loads(out.read_text())
    return {"size": size, "context_views": count, "seconds_per_step": figures["seconds_per_step"],
            "peak_gib": figures["peak_memory_gib"], "before_fit_gib": figures["rss_before_fit_gib"],
            "threads": figures["threads"], "batch_size": figures["batch_size"], "steps": steps,
            "warmup": warmup, "load_1min": round(os.getloadavg()[0], 2)}  # fmt: skip


# ----------------------------------------------------------------------------------------------- computed


def paper_network() -> tuple[dict, dict]:
    """The network settings (``model.net``) and data settings of the paper's configuration."""
    import yaml

    cfg = yaml.safe_load((REPO / PAPER_CONFIG).read_text())
    return cfg["model"]["net"], cfg["data"]


def forward_flops(counts: list[int]) -> list[dict]:
    """FLOPs of one forward of the paper's network (batch 1, one target view) per count of context views,
    by part. On the meta device: shapes only, so the ``large`` network costs no memory and no time."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from aesplat.model import build_model

    net, data = paper_network()
    side = int(data["image_size"])
    targets = int(data.get("num_target_views", 1))
    batch = int(data["batch_size"])
    # torch.autocast has no meta device; the network only ever turns it off (fp32 geometry), as here.
    with mock.patch("torch.autocast", lambda *a, **k: contextlib.nullcontext()), torch.device("meta"):
        model = build_model(size=net["size"], appearance=net["appearance"], sh_degree=net["sh_degree"],
                            view_aggregation="pool")  # fmt: skip
        patch = model.cfg.encoder.patch_size
        tokens = (side // patch) ** 2 + model.aggregator.patch_start
        relation, colour = model.appearance.gvsre.mlp, model.appearance.wcm.mlp  # Linear, GELU, Linear
        # Floats the pool head keeps for the backward per (Gaussian, view) pair of each MLP: its input and
        # its hidden layer before and after the GELU (the concatenations and masks beside them not counted).
        per_relation = relation[0].in_features + 2 * relation[0].out_features
        per_colour = colour[0].in_features + 2 * colour[0].out_features
        rows = []
        for k in counts:
            with FlopCounterMode(display=False) as counter:
                model(torch.empty(1, k, 3, side, side), torch.empty(1, targets, 3, side, side))
            by_module = counter.get_flop_counts()
            gflops = {name: _gflops(by_module, name) for name in PARTS}
            attention = _gflops(by_module, "aggregator", "aten.bmm") - _gflops(
                by_module, "aggregator.patch_embed", "aten.bmm"
            )  # the alternating blocks' attention (the aggregator's minus its patch encoder's)
            rows.append({
                "context_views": k, "target_views": targets, "image_size": side, "tokens_per_view": tokens,
                "global_tokens": (k + targets) * tokens, "gaussians": k * side * side,
                "pool_pairs": k * k * side * side, "gflops": counter.get_total_flops() / 1e9,
                "batch_size": batch, "pool_saved_gib": 4 * batch * side * side
                * (k * k * per_relation + k * (k - 1) * per_colour) / 2**30,
                "encoder_gflops": gflops["aggregator.patch_embed"], "attention_gflops": attention,
                "transformer_other_gflops": gflops["aggregator"] - gflops["aggregator.patch_embed"] - attention,
                "heads_gflops": gflops["depth_head"] + gflops["gaussian_head"] + gflops["camera_head"],
                "appearance_gflops": gflops["appearance"],
            })  # fmt: skip
    return rows


def _gflops(by_module: dict, name: str, op: str | None = None) -> float:
    """GFLOPs the counter gave the network's module ``name`` (only operator ``op``, e.g. ``aten.bmm``)."""
    ops = by_module.get(f"AESplatModel.{name}", {})
    return sum(v for o, v in ops.items() if op is None or str(o) == op) / 1e9


# ----------------------------------------------------------------------------------------------- report


def markdown(record: dict) -> str:
    measured, computed, meta = record["measured"], record["computed"], record["meta"]
    machine, load = meta["machine"], meta["load"]
    out = [
        "Measured on the CPU: the demo's `tiny` network with the `pool` head, batch 2, one target view, "
        f"{measured[0]['threads'] if measured else '?'} torch thread(s); the median of "
        f"{measured[0]['steps'] if measured else '?'} training steps after "
        f"{measured[0]['warmup'] if measured else '?'} (`benchmarks/bench_train_step.py`, one process per "
        f"point). {machine['cpu']}, {machine['cores']} cores, torch {machine.get('torch', '?')}; "
        f"{meta['date'][:16]} UTC, commit {meta['commit']}{' (modified)' if meta['modified'] else ''}; "
        f"1-minute load average {load['start'][0] if load['start'] else '?'} at the start, "
        f"{load['end'][0]} at the end.",
        "",
        "| side | context views | s per step | × 2 views | peak memory (GiB) | above start (GiB) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    base = {m["size"]: m for m in measured if m["context_views"] == 2}
    for m in measured:
        two = base.get(m["size"])
        ratio = m["seconds_per_step"] / two["seconds_per_step"] if two else float("nan")
        out.append(f"| {m['size']} | {m['context_views']} | {m['seconds_per_step']:.3f} | {ratio:.2f} | "
                   f"{m['peak_gib']:.2f} | {m['peak_gib'] - m['before_fit_gib']:.3f} |")  # fmt: skip
    c0 = computed[0] if computed else {}
    out += [
        "",
        f"Computed for `{PAPER_CONFIG}` (the `large` network, {c0.get('image_size')}², "
        f"{c0.get('tokens_per_view')} tokens per view, {c0.get('target_views')} target view, batch 1): "
        "GFLOPs of one model forward, counted on the meta device, and of it the geometry transformer's "
        "attention and the appearance head; a training step adds the backward, about twice the forward, and "
        "the rendering of the targets. Pool pairs: what the `pool` head keeps for the backward of its two "
        f"per-pair MLPs at the configuration's batch of {c0.get('batch_size')} (float32; by formula, a lower "
        "bound).",
        "",
        "| context views | tokens (global) | Gaussians | GFLOPs | attention | appearance | pool pairs, GiB |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for c in computed:
        out.append(f"| {c['context_views']} | {c['global_tokens']:,} | {c['gaussians']:,} | {c['gflops']:,.0f} "
                   f"| {c['attention_gflops']:,.0f} | {c['appearance_gflops']:,.1f} | "
                   f"{c['pool_saved_gib']:.2f} |")  # fmt: skip
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--counts", type=int, nargs="+", default=[2, 3, 4, 5, 6], help="context views per step")
    p.add_argument("--sizes", type=int, nargs="+", default=[42, 224], help="image sides measured on the CPU")
    p.add_argument("--steps", type=int, default=15, help="timed steps per point (default 15)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    p.add_argument("--out", default=str(REPO / "docs" / "results" / "context_views"), help="report folder")
    a = p.parse_args(argv)
    if min(a.counts) < 2 or 2 not in a.counts or a.steps < 1 or a.warmup < 0:
        p.error("--counts must include 2 and be >= 2; --steps >= 1, --warmup >= 0")
    out = Path(a.out)
    load_start = [round(v, 2) for v in os.getloadavg()]
    path = out / "cost.json"
    settings = {"steps": a.steps, "warmup": a.warmup, "config": CONFIG}
    done = []
    if path.exists():
        saved = json.loads(path.read_text())
        if saved.get("settings") == settings:
            done = saved["measured"]
    measured = []
    for size in sorted(set(a.sizes)):
        for k in sorted(set(a.counts)):
            kept = next((m for m in done if (m["size"], m["context_views"]) == (size, k)), None)
            if kept is None:
                print(f"[measure] {size}², {k} context views", flush=True)
                kept = measure(size, k, a.steps, a.warmup)
            measured.append(kept)
            record = {"settings": settings, "measured": measured, "computed": [],
                      "meta": provenance(load_start)}  # fmt: skip
            write_whole(path, (json.dumps(record, indent=1) + "\n").encode())  # each point, as it is done
    import torch  # noqa: F401 - provenance() names the torch version of a process that imported it

    record["computed"] = forward_flops(sorted(set(a.counts)))
    record["meta"] = provenance(load_start)
    write_whole(path, (json.dumps(record, indent=1) + "\n").encode())
    write_whole(out / "cost.md", markdown(record).encode())
    print(f"wrote {path} and {out / 'cost.md'}")


if __name__ == "__main__":
    sys.exit(main())
