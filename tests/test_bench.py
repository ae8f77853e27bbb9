"""`aesplat bench`: the sweep, its measurements (checked against a direct render) and its report files."""

import csv
import json
import math
from dataclasses import replace

import pytest
import torch
from PIL import Image

from aesplat.bench.command import main
from aesplat.bench.report import change_cell, markdown_tables, speedup_cell, with_interval, write_report
from aesplat.bench.run import Bench, Row, contexts_of, resize_views
from aesplat.bench.sweep import Point, Setting, default_sweep, model_input_sizes
from aesplat.model import build_model, dataset_cameras
from aesplat.render import render
from aesplat.train.metrics import psnr
from aesplat.types import BatchedExample, BatchedViews
from tests.helpers import SH_DEGREE, aesplat, identity_views, make_shards, one_line, write_tiny_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")

SIZE = 28


def views(v: int, size: int = SIZE) -> BatchedViews:
    return identity_views(v, size)


@pytest.fixture(scope="module")
def model() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model(size="tiny", sh_degree=SH_DEGREE, near=0.1, far=20.0).eval()


@pytest.fixture(scope="module")
def scenes() -> list[BatchedExample]:
    torch.manual_seed(1)
    return [BatchedExample(context=views(2), target=views(2), scene=[f"s{i}"]) for i in range(2)]


# ----------------------------------------------------------------------------------------------- the sweep


def test_default_sweep_varies_one_knob_at_a_time_from_the_baseline():
    baseline, points = default_sweep(4, 224, backends=("torch",), tile_sizes=(8, 16), compiled=True)
    # Knowing the baseline's own count of context views and tile side, those points are the baseline itself.
    _, known = default_sweep(4, 224, knobs=["context_views", "tile_size"], base_context_views=2,
                             tile_sizes=(8, 16), base_tile_size=8)  # fmt: skip
    assert [p.setting == baseline for p in known] == [True, False, False, False, True, False]
    assert [p.label for p in known] == ["2 views", "3 views", "4 views", "6 views", "tile 8", "tile 16"]
    assert baseline == Setting(backend="torch")
    knobs = list(dict.fromkeys(p.knob for p in points))
    assert knobs == ["sh_degree", "context_views", "input_size", "render_size", "keep_fraction", "min_opacity",
                     "precision", "backend", "tile_size"]  # fmt: skip
    # Every series but the tile sizes (16 is not the baseline's None) and the context views (the baseline
    # feeds every view a sample holds, whatever their number) holds the baseline.
    for knob in (k for k in knobs if k not in ("tile_size", "context_views")):
        assert sum(p.setting == baseline for p in points if p.knob == knob) == 1, knob
    assert [p.label for p in points if p.knob == "context_views"] == [
        "2 views",
        "3 views",
        "4 views",
        "6 views",
    ]
    for p in points:  # each point differs from the baseline in its own knob only
        changed = {k for k in vars(baseline) if getattr(p.setting, k) != getattr(baseline, k)}
        assert changed <= {p.knob, "render_options"}, (p, changed)
    assert [p.label for p in points if p.knob == "sh_degree"] == ["SH 0", "SH 1", "SH 2", "SH 3", "SH 4"]
    assert ("compile", True) in [o for p in points for o in p.setting.render_options]
    assert len(default_sweep(2, 28, knobs=["precision"])[1]) == 2
    with pytest.raises(ValueError, match="unknown knob"):
        default_sweep(2, 28, knobs=["colour"])


def test_model_input_sizes_are_multiples_of_the_patch():
    sizes = model_input_sizes(224, [0.5, 0.75, 1.0, 0.1], patch=14)
    assert sizes == [28, 112, 168, 224] and all(s % 14 == 0 for s in sizes)
    assert model_input_sizes(21, [0.5, 1.0], patch=7) == [14, 21]  # a model built with 7-pixel patches
    _, points = default_sweep(2, 35, patch=7, knobs=["input_size"], input_scales=(0.4, 0.6, 1.0))
    assert [p.setting.input_size for p in points] == [14, 21, None]


def test_resize_views_keeps_normalised_intrinsics():
    v = views(2, 28)
    small = resize_views(v, 14)
    assert small.images.shape == (1, 2, 3, 14, 14)
    assert small.intrinsics is v.intrinsics and resize_views(v, None) is v and resize_views(v, 28) is v


# ----------------------------------------------------------------------------------------------- measuring


def test_bench_figures_match_a_direct_render(model, scenes):
    background = torch.tensor([0.2, 0.3, 0.4])
    baseline, points = default_sweep(SH_DEGREE, SIZE, knobs=["sh_degree", "render_size", "keep_fraction"],
                                     render_scales=(0.5, 1.0), keep_fractions=(0.5,))  # fmt: skip
    points = [p for p in points if p.label != "SH 1"]
    scenes = scenes[:1]
    bench = Bench(model, scenes, torch.device("cpu"), repeats=1, warmup=0,
                  render_kwargs={"background": background}, progress=False)  # fmt: skip
    rows = bench.run(points, baseline, warmup_runs=0)
    by = {(r.knob, r.label): r for r in rows}

    # The baseline, measured here by hand: predicted target cameras, every SH band, full size.
    want = []
    with torch.no_grad():
        for scene in scenes:
            out = model(scene.context.images, scene.target.images)
            img = render(out.gaussians, out.extrinsics[:, 2:], out.intrinsics[:, 2:], SIZE, SIZE,
                         background=background).color[0]  # fmt: skip
            want += psnr(img, scene.target.images[0]).tolist()
    full = by[("sh_degree", f"SH {SH_DEGREE}")]
    assert full.baseline and full.psnr == pytest.approx(sum(want) / len(want), abs=1e-4)
    # Shared settings are one measurement: the full-size render and all Gaussians are the same baseline row.
    for key in (("render_size", f"{SIZE} px"), ("keep_fraction", "100 %")):
        assert by[key].baseline and by[key].psnr == full.psnr and by[key].render_ms == full.render_ms
    assert sum(r.baseline for r in rows) == 3
    assert by[("sh_degree", "SH 0")].psnr != full.psnr  # higher bands of a random model are not silent
    assert by[("keep_fraction", "50 %")].gaussians == full.gaussians / 2 == SIZE * SIZE
    for r in rows:
        assert not r.skipped and -1 <= r.ssim <= 1 and math.isfinite(r.psnr)
        assert r.forward_ms > 0 and r.render_ms > 0 and r.total_ms == pytest.approx(r.forward_ms + r.render_ms)
    # Only the forward key (input size, precision) triggers model runs: one here for all points.
    assert len(bench._forwards) == 1


def test_bench_with_the_data_sets_cameras_renders_from_them(model, scenes):
    """A checkpoint trained with model.cameras=dataset is measured with each scene's own target cameras."""
    turned = torch.eye(4).repeat(1, 2, 1, 1)
    turned[0, 1, :3, 3] = torch.tensor([0.3, -0.1, 0.2])
    scene = replace(scenes[0], target=replace(scenes[0].target, extrinsics=turned))
    setting = Setting()
    (fwd,) = Bench(model, [scene], torch.device("cpu"), repeats=1, warmup=0, progress=False,
                   cameras="dataset").forward(setting)  # fmt: skip
    extrinsics, intrinsics = dataset_cameras(scene)
    assert torch.equal(fwd.extrinsics, extrinsics[:, 2:]) and torch.equal(fwd.intrinsics, intrinsics[:, 2:])
    (own,) = Bench(model, [scene], torch.device("cpu"), repeats=1, warmup=0, progress=False).forward(setting)
    assert not torch.equal(own.extrinsics, fwd.extrinsics)  # the camera head predicts something else


def test_input_size_and_precision_run_their_own_forward(model, scenes):
    base = Setting()
    points = [Point("input_size", "14 px", replace(base, input_size=14)), Point("precision", "bf16",
              replace(base, precision="bf16")), Point("precision", "fp32", base)]  # fmt: skip
    bench = Bench(model, scenes[:1], torch.device("cpu"), repeats=1, warmup=0, progress=False)
    rows = bench.run(points, base, warmup_runs=1)
    assert len(bench._forwards) == 3
    small = bench._forwards[(None, 14, "fp32")][0]
    assert small.gaussians.num_gaussians == 2 * 14 * 14  # one Gaussian per input pixel
    assert all(not r.skipped for r in rows), [r.skipped for r in rows]
    assert rows[0].gaussians == 2 * 14 * 14 and rows[2].gaussians == 2 * SIZE * SIZE


def _labelled(key: str, v: int, first: int = 0) -> BatchedExample:
    """A scene ``key`` whose context views are frames first, first + 1, ..."""
    context = replace(views(v), index=torch.arange(first, first + v)[None])
    return BatchedExample(context=context, target=views(1), scene=[key])


def test_contexts_of_matches_the_scenes_by_key_in_the_shards_order():
    # The 3-view stream leaves out b (no 3-view context) and holds x, a scene the other count left out.
    stream = [_labelled("a", 3, 10), _labelled("x", 3, 20), _labelled("c", 3, 30), _labelled("d", 3, 40)]
    read = []

    def reading():
        for scene in stream:
            read.append(scene.scene[0])
            yield scene

    out = contexts_of(reading(), ["a", "b", "c"])
    assert [None if c is None else c.index[0, 0].item() for c in out] == [10, None, 30]
    assert read == ["a", "x", "c"]  # read no further than the last scene wanted
    assert contexts_of(iter(stream[:1]), ["a", "b"])[1] is None  # the stream ends: b has none


def test_the_context_views_knob_feeds_each_count_and_renders_the_same_targets():
    torch.manual_seed(0)
    pool = build_model(size="tiny", sh_degree=SH_DEGREE, near=0.1, far=20.0, view_aggregation="pool").eval()
    gen = torch.Generator().manual_seed(3)

    def context(v: int, first: int) -> BatchedViews:
        return replace(views(v), index=torch.arange(first, first + v)[None],
                       images=torch.rand(1, v, 3, SIZE, SIZE, generator=gen))  # fmt: skip

    scenes = [BatchedExample(context=context(2, 0), target=views(2), scene=[f"s{i}"]) for i in range(2)]
    contexts = {3: [context(3, 10), context(3, 20)], 4: [context(4, 30), context(4, 40)],
                6: [context(6, 50), None]}  # s1 carries no 6-view context  # fmt: skip
    baseline, points = default_sweep(SH_DEGREE, SIZE, knobs=["context_views"])
    bench = Bench(pool, scenes, torch.device("cpu"), repeats=1, warmup=0, progress=False, contexts=contexts)
    rows = {r.label: r for r in bench.run(points, baseline, warmup_runs=0)}
    assert "1 of 2 scenes (s1) carry no 6-view context" in rows["6 views"].skipped
    for count in (2, 3, 4):
        row = rows[f"{count} views"]
        assert not row.skipped and row.gaussians == count * SIZE * SIZE
        psnrs = []
        for i, scene in enumerate(scenes):
            fed = scene.context if count == 2 else contexts[count][i]
            with torch.no_grad():  # the same targets, rendered from the Gaussians of that count's context
                out = pool(fed.images, scene.target.images)
                img = render(out.gaussians, out.extrinsics[:, count:], out.intrinsics[:, count:], SIZE,
                             SIZE).color  # fmt: skip
            psnrs += psnr(img[0], scene.target.images[0]).tolist()
        assert row.psnr == pytest.approx(sum(psnrs) / len(psnrs), abs=1e-4)
        assert math.isfinite(row.rot_err_deg)
    assert len({rows[f"{c} views"].psnr for c in (2, 3, 4)}) == 3
    # The paper's head takes its own count only: the others are reported, not fatal.
    concat = Bench(build_model(size="tiny", sh_degree=SH_DEGREE), scenes, torch.device("cpu"), repeats=1,
                   warmup=0, progress=False, contexts=contexts)  # fmt: skip
    concat_rows = {r.label: r for r in concat.run(points, baseline, warmup_runs=1)}
    assert not concat_rows["2 views"].skipped
    assert "view_aggregation: pool" in concat_rows["3 views"].skipped


def test_a_failing_setting_is_reported_not_fatal(model, scenes):
    base = Setting()
    points = [Point("backend", "nope", replace(base, backend="nope")), Point("backend", "torch", base)]
    bench = Bench(model, scenes[:1], torch.device("cpu"), repeats=1, warmup=0, progress=False)
    rows = bench.run(points, base, warmup_runs=0)
    assert "unknown render backend" in rows[0].skipped and math.isnan(rows[0].psnr)
    assert not rows[1].skipped
    table = markdown_tables(rows, {})
    assert "Not measured here: nope (ValueError: unknown render backend" in table  # a line, not a table row
    assert "| nope |" not in table and "| **torch** |" in table
    with pytest.raises(ValueError, match="the baseline setting cannot run here: .*unknown render backend"):
        bench.run(points[:1], points[0].setting, warmup_runs=0)


# ----------------------------------------------------------------------------------------------- report


def fake_rows() -> list[Row]:
    """SH 0 measurably faster and worse, SH 1 no measurable difference in either, SH 2 the baseline; precision
    fp32 the baseline again, bf16 skipped."""
    timing = dict(forward_ms=10.0, forward_ms_lo=9.0, forward_ms_hi=11.0, render_ms_lo=4.0, total_ms_lo=14.0,
                  render_ms_hi=9.0, total_ms_hi=19.0, gaussians=100)  # fmt: skip
    rows = [
        Row("sh_degree", "SH 0", psnr=20.0, psnr_delta=-2.0, psnr_delta_lo=-2.5, psnr_delta_hi=-1.5, ssim=0.5,
            ssim_delta=-0.2, ssim_delta_lo=-0.3, ssim_delta_hi=-0.1, render_ms=5.0, total_ms=15.0, speedup=1.13,
            speedup_lo=1.05, speedup_hi=1.2, **timing),
        Row("sh_degree", "SH 1", psnr=21.0, psnr_delta=-1.0, psnr_delta_lo=-2.5, psnr_delta_hi=0.5, ssim=0.6,
            ssim_delta=0.0, ssim_delta_lo=0.0, ssim_delta_hi=0.0, render_ms=6.0, total_ms=16.0, speedup=1.02,
            speedup_lo=0.97, speedup_hi=1.08, **timing),
        Row("sh_degree", "SH 2", psnr=22.0, psnr_delta=0.0, psnr_delta_lo=0.0, psnr_delta_hi=0.0, ssim=0.7,
            ssim_delta=0.0, ssim_delta_lo=0.0, ssim_delta_hi=0.0, render_ms=7.0, total_ms=17.0, speedup=1.0,
            speedup_lo=1.0, speedup_hi=1.0, baseline=True, **timing),
    ]  # fmt: skip
    rows.append(replace(rows[2], knob="precision", label="fp32"))
    rows.append(Row("precision", "bf16", skipped="RuntimeError: no bf16 here"))
    return rows


def test_write_report_files(tmp_path):
    load = {"load_before": [1.5, 1, 1], "load_after": [2.25, 1, 1], "other_cores": 1.03, "cpu_count": 2,
            "seconds": 30.0}  # fmt: skip
    meta = {"ckpt": "x.ckpt", "scenes": 3, "repeats": 9, "round_scenes": 2, "threads": 2, "load": load,
            "warning": "aesplat bench: warning: other processes kept 1.0 of 2 cores"}  # fmt: skip
    paths = write_report(fake_rows(), tmp_path / "b", meta)
    with open(paths["bench.csv"]) as f:
        table = list(csv.DictReader(f))
    # The measured rows only, every timing with its interval.
    assert [r["label"] for r in table] == ["SH 0", "SH 1", "SH 2", "fp32"] and float(table[1]["psnr"]) == 21.0
    for column in ("forward_ms", "render_ms", "total_ms", "speedup", "psnr_delta", "ssim_delta"):
        assert {column, f"{column}_lo", f"{column}_hi"} <= set(table[0]), column
    assert float(table[0]["total_ms_lo"]) == 14.0 and float(table[0]["speedup_hi"]) == 1.2
    md = paths["BENCH.md"].read_text()
    assert "## SH degree at render" in md and "## model precision" in md
    assert "| SH 0 | 20.00 | -2.00 (-2.50 to -1.50) | 0.5000 | -0.2000 (-0.3000 to -0.1000) | – | 100 |" in md
    assert "| SH 0 | 10.0 (9.0–11.0) | 5.0 (4.0–9.0) | 15.0 (14.0–19.0) | 1.13× (1.05–1.20×) |" in md
    assert "| SH 1 | 21.00 | no measurable difference (-2.50 to +0.50) | 0.6000 | same images | – | 100 |" in md
    assert ("| SH 1 | 10.0 (9.0–11.0) | 6.0 (4.0–9.0) | 16.0 (14.0–19.0) "
            "| no measurable difference (0.97–1.08×) |") in md  # fmt: skip
    assert "| **SH 2** | 22.00 | baseline | 0.7000 | baseline |" in md
    assert "| bf16 |" not in md and "Not measured here: bf16 (RuntimeError: no bf16 here)." in md
    assert "load average 1.50 before, 2.25 after; other processes kept 1.03 of 2 cores busy" in md
    assert "**aesplat bench: warning: other processes kept 1.0 of 2 cores**" in md
    assert "the median over 9 rounds" in md and "on 2 of the scenes" in md
    assert Image.open(paths["accuracy_vs_time.png"]).size[0] > 500
    saved = json.loads(paths["bench.json"].read_text())
    assert saved["meta"]["ckpt"] == "x.ckpt" and len(saved["rows"]) == 5 and saved["rows"][4]["skipped"]


def test_report_cells_say_which_differences_are_measurable():
    row = Row("k", "x", speedup=0.8, speedup_lo=0.7, speedup_hi=0.9)
    assert speedup_cell(row) == "0.80× (0.70–0.90×)"  # measurably slower: a ratio below 1 with its interval
    assert speedup_cell(replace(row, speedup_hi=1.0)) == "no measurable difference (0.70–1.00×)"
    assert speedup_cell(replace(row, speedup_lo=math.nan, speedup_hi=math.nan)).startswith("0.80×, untested")
    assert speedup_cell(replace(row, baseline=True)) == "baseline"
    change = Row("k", "x", psnr_delta=0.3, psnr_delta_lo=0.1, psnr_delta_hi=0.5)
    assert change_cell(change, "psnr", 2) == "+0.30 (+0.10 to +0.50)"
    assert (
        change_cell(replace(change, psnr_delta_lo=-0.1), "psnr", 2)
        == "no measurable difference (-0.10 to +0.50)"
    )
    assert change_cell(replace(change, psnr_delta_lo=math.nan), "psnr", 2) == "+0.30, untested (one scene)"
    assert (
        change_cell(replace(change, psnr_delta_lo=0.3, psnr_delta_hi=0.3), "psnr", 2) == "+0.30 in every scene"
    )
    assert (
        with_interval(21.61, 21.2, 22.04) == "21.6 (21.2–22.0)" and with_interval(3.0, math.nan, 4.0) == "3.0"
    )


# ----------------------------------------------------------------------------------------------- command line


def test_bench_command_end_to_end(tmp_path, pretend_gsplat):
    """On a (pretended) GPU node with `--device cpu`: the CPU tensors are rendered by the torch backend."""
    make_shards(tmp_path, SIZE, frames=10, height=32, width=40, scenes=1, test_scenes=2, seed=0)
    ckpt = write_tiny_checkpoint(tmp_path / "run", data_root=str(tmp_path / "shards"), image_size=SIZE)
    assert main(["--ckpt", str(ckpt), "--knobs", "render_size,min_opacity", "--render-scales", "1",
                 "--min-opacities", "0.5", "--scenes", "1", "--repeats", "1", "--warmup", "0",
                 "--process-warmup", "0", "--no-progress", "--device", "cpu"]) == 0  # fmt: skip
    out = tmp_path / "run" / "bench"  # the default: next to the run
    rows = json.loads((out / "bench.json").read_text())["rows"]
    labels = [(r["knob"], r["label"]) for r in rows]
    assert labels == [("render_size", f"{SIZE} px"), ("min_opacity", "≥ 0"), ("min_opacity", "≥ 0.5")]
    assert all(not r["skipped"] for r in rows) and rows[0]["baseline"] and rows[1]["baseline"]
    assert {r["setting"]["backend"] for r in rows} == {"torch"}
    assert rows[0]["psnr"] == rows[1]["psnr"] and rows[2]["gaussians"] <= rows[1]["gaussians"]
    assert (out / "accuracy_vs_time.png").is_file() and (out / "bench.csv").is_file()
    with pytest.raises(SystemExit, match="no shards"):
        main(["--ckpt", str(ckpt), "--data-root", str(tmp_path / "empty"), "--no-progress", "--device", "cpu"])


KNOBS = (
    "sh_degree, context_views, input_size, render_size, keep_fraction, min_opacity, precision, backend, "
    "tile_size"
)
HELP = "(`aesplat bench --help` lists the options)"


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory, shards):
    """A checkpoint whose run reads ``shards``: a bad argument, not a missing file, is what stops the bench."""
    return write_tiny_checkpoint(tmp_path_factory.mktemp("bench_run"), data_root=str(shards), image_size=SIZE)


# A bad argument of `aesplat bench`, its exit status, the line it gives (less "aesplat bench: ").
BAD_ARGUMENTS = [
    (["--repeats", "0"], 1, "--repeats 0: it must be 1 or more"),
    (["--repeats", "-1"], 1, "--repeats -1: it must be 1 or more"),
    (["--scenes", "-3"], 1, "--scenes -3: it must be 1 or more"),
    (["--scenes", "0"], 1, "--scenes 0: it must be 1 or more"),
    (["--round-scenes", "0"], 1, "--round-scenes 0: it must be 1 or more"),
    (["--round-scenes", "-2"], 1, "--round-scenes -2: it must be 1 or more"),
    (["--warmup", "-1"], 1, "--warmup -1: it must be 0 or more"),
    (["--process-warmup", "-1"], 1, "--process-warmup -1: it must be 0 or more"),
    (["--threads", "0"], 1, "--threads 0: it must be 1 or more"),
    (["--image-size", "0"], 1, "--image-size 0: it must be 1 or more pixels"),
    (["--data-context-views", "1"], 1, "--data-context-views 1: it must be 2 or more"),
    (["--context-views", "1"], 1, "--context-views 1: each must be a count of 2 or more"),
    (["--context-views="], 1, "--context-views '': it must list one or more values, each a count of 2 or more"),
    (["--context-views", "2,x"], 2,
     f"argument --context-views: '2,x' is not a comma-separated list of whole numbers {HELP}"),
    (["--knobs", "foo"], 1, f"--knobs foo: each must be one of {KNOBS}"),
    (["--knobs", ","], 1, f"--knobs '': it must list one or more values, each one of {KNOBS}"),
    (["--knobs", "render_size,render_size"], 1, "--knobs render_size,render_size: it gives render_size twice"),
    (["--input-scales", "nan"], 1, "--input-scales nan: each must be a finite number more than 0"),
    (["--input-scales", "0"], 1, "--input-scales 0: each must be a finite number more than 0"),
    (["--input-scales", "inf"], 1, "--input-scales inf: each must be a finite number more than 0"),
    (["--render-scales", "0.5,nan"], 1, "--render-scales 0.5,nan: each must be a finite number more than 0"),
    (["--render-scales", "-1"], 1, "--render-scales -1: each must be a finite number more than 0"),
    (["--render-scales", "inf"], 1, "--render-scales inf: each must be a finite number more than 0"),
    (["--keep-fractions", "0"], 1, "--keep-fractions 0: each must be a fraction in (0, 1]"),
    (["--keep-fractions", "1.5"], 1, "--keep-fractions 1.5: each must be a fraction in (0, 1]"),
    (["--keep-fractions", "nan"], 1, "--keep-fractions nan: each must be a fraction in (0, 1]"),
    (["--min-opacities", "1"], 1, "--min-opacities 1: each must be an opacity in [0, 1)"),
    (["--min-opacities", "-0.5"], 1, "--min-opacities -0.5: each must be an opacity in [0, 1)"),
    (["--min-opacities", "nan"], 1, "--min-opacities nan: each must be an opacity in [0, 1)"),
    (["--precisions", "fp16"], 1, "--precisions fp16: each must be one of fp32, bf16"),
    (["--precisions", "fp32,fp32"], 1, "--precisions fp32,fp32: it gives fp32 twice"),
    (["--backends", "foo"], 1, "--backends foo: each must be one of torch, gsplat"),
    (["--backends", "torch,torch"], 1, "--backends torch,torch: it gives torch twice"),
    (["--tile-sizes", "nan"], 1, "--tile-sizes nan: each must be a whole number of pixels, 1 or more"),
    (["--tile-sizes", "0"], 1, "--tile-sizes 0: each must be a whole number of pixels, 1 or more"),
    (["--tile-sizes", "8.5"], 1, "--tile-sizes 8.5: each must be a whole number of pixels, 1 or more"),
    (["--tile-sizes", "-8"], 1, "--tile-sizes -8: each must be a whole number of pixels, 1 or more"),
    (["--tile-sizes", "inf"], 1, "--tile-sizes inf: each must be a whole number of pixels, 1 or more"),
    (["--tile-sizes", "8,x"], 2,
     f"argument --tile-sizes: '8,x' is not a comma-separated list of numbers {HELP}"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("bad", "status", "message"), BAD_ARGUMENTS, ids=[" ".join(c[0]) for c in BAD_ARGUMENTS]
)
def test_bench_refuses_a_bad_argument_in_one_line_before_any_work(bad, status, message, tiny_ckpt, capsys,
                                                                   tmp_path):  # fmt: skip
    """A count, size, scale or name out of range stops `aesplat bench` with one line naming the option, the
    value given and what it must be; nothing is written (the quick settings keep short a bench that runs)."""
    quick = ["--scenes", "1", "--repeats", "1", "--process-warmup", "0", "--knobs", "render_size",
             "--render-scales", "1", "--no-progress", "--device", "cpu"]  # fmt: skip
    code, err = aesplat(
        capsys, "bench", "--ckpt", str(tiny_ckpt), "--out", str(tmp_path / "bench"), *quick, *bad
    )
    assert (code, one_line(err)) == (status, f"aesplat bench: {message}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_bench_command_on_cuda(tmp_path):
    """`aesplat bench --device cuda`: gsplat (if installed) and torch backends, fp32 and bf16, all measured."""
    from aesplat.render import gsplat_available

    make_shards(tmp_path, SIZE, frames=10, height=32, width=40, scenes=1, test_scenes=2, seed=0)
    ckpt = write_tiny_checkpoint(tmp_path / "run", data_root=str(tmp_path / "shards"), image_size=SIZE)
    assert main(["--ckpt", str(ckpt), "--device", "cuda", "--knobs", "backend,precision", "--scenes", "2",
                 "--repeats", "2", "--warmup", "1", "--process-warmup", "1", "--no-progress"]) == 0  # fmt: skip
    saved = json.loads((tmp_path / "run" / "bench" / "bench.json").read_text())
    assert saved["meta"]["device"].startswith("cuda")
    rows = {(r["knob"], r["label"]): r for r in saved["rows"]}
    backends = {"gsplat", "torch"} if gsplat_available() else {"torch"}
    assert {label for knob, label in rows if knob == "backend"} == backends
    assert {label for knob, label in rows if knob == "precision"} == {"fp32", "bf16"}
    for (knob, label), row in rows.items():
        if (knob, label) == ("precision", "bf16") and not torch.cuda.is_bf16_supported():
            continue
        assert not row["skipped"], (knob, label, row["skipped"])
        assert math.isfinite(row["psnr"]) and row["total_ms"] > 0, (knob, label)
    if gsplat_available():  # the same Gaussians through both rasterizers
        assert abs(rows[("backend", "gsplat")]["psnr"] - rows[("backend", "torch")]["psnr"]) < 0.5
