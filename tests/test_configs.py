"""Every shipped config, and every way the repository layers them, parses; overlays change what they mean to.

The command lines are the ones the config files quote in their header comments (run in-process with
``--print_config``); each shipped config must be quoted by at least one of them.
"""

from __future__ import annotations

import shlex

import pytest
import yaml

from aesplat import cli
from aesplat.lightning_cli import removed_key_error
from aesplat.model import ModelConfig, NetConfig
from aesplat.render import RasterizerConfig
from tests.helpers import REPO

pytestmark = pytest.mark.filterwarnings("ignore:LightningCLI's args parameter")
CONFIGS = sorted(str(p.relative_to(REPO)) for p in (REPO / "conf").rglob("*.yaml"))


def header_commands() -> dict[str, list[str]]:
    """The `aesplat fit|test …` lines of the configs' header comments, without ``[…]`` parts and comments."""
    commands = {}
    for config in CONFIGS:
        for line in (REPO / config).read_text().splitlines():
            if not line.startswith("#   aesplat "):
                continue
            line = line[1:].split("  #")[0]
            while "[" in line:
                start = line.index("[")
                line = line[:start] + line[line.index("]", start) + 1 :]
            commands[line.strip()] = shlex.split(line)[1:]
    return commands


COMMANDS = header_commands()


@pytest.fixture(scope="module")
def parsed() -> dict[str, dict]:
    """Each header command's config as `--print_config` writes it, parsed."""
    return {line: print_config(argv) for line, argv in COMMANDS.items()}


def print_config(argv: list[str]) -> dict:
    import contextlib
    import io
    import os

    out, cwd = io.StringIO(), os.getcwd()
    os.chdir(REPO)
    try:
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as info:
            cli.main([*argv, "--print_config"])
    finally:
        os.chdir(cwd)
    assert info.value.code in (0, None), info.value.code
    return yaml.safe_load(out.getvalue())


def config_of(parsed: dict[str, dict], *files: str, command: str = "fit") -> dict:
    """The parsed config of the header command that layers exactly ``files`` (in this order)."""
    for line, argv in COMMANDS.items():
        if argv[0] == command and [argv[i + 1] for i, a in enumerate(argv) if a == "-c"] == list(files):
            return parsed[line]
    raise AssertionError(f"no config header quotes `aesplat {command}` of {' + '.join(files)}")


def differences(a: dict, b: dict, prefix: str = "") -> set[str]:
    """Dotted keys whose values differ between two nested dicts."""
    keys = set(a) | set(b)
    out = set()
    for key in keys:
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            out |= differences(x, y, f"{prefix}{key}.")
        elif x != y:
            out.add(f"{prefix}{key}")
    return out


def test_every_shipped_config_is_quoted_by_a_header_command():
    quoted = {argv[i + 1] for argv in COMMANDS.values() for i, a in enumerate(argv) if a == "-c"}
    assert set(CONFIGS) <= quoted, f"configs no header command uses: {sorted(set(CONFIGS) - quoted)}"


def test_every_header_command_parses(parsed):
    for line, config in parsed.items():
        assert {"model", "data", "trainer"} <= set(config), line
        assert config["model"]["net"]["size"] in ("tiny", "base", "large"), line


def test_acid_is_re10k_with_its_own_data_and_names(parsed):
    re10k, acid = config_of(parsed, "conf/re10k.yaml"), config_of(parsed, "conf/re10k.yaml", "conf/acid.yaml")
    assert (
        acid["data"]["root"] == "outputs/shards/acid" and acid["trainer"]["default_root_dir"] == "outputs/acid"
    )
    assert acid["wandb"]["name"] == "acid" and acid["wandb"]["tags"] == ["acid", "full"]
    assert differences(re10k, acid) == {"data.root", "trainer.default_root_dir", "wandb.name", "wandb.tags"}


def test_demo_from_scratch_is_the_demo_from_a_random_start(parsed):
    demo = config_of(parsed, "conf/demo.yaml")
    scratch = config_of(parsed, "conf/demo.yaml", "conf/demo_from_scratch.yaml")
    assert (
        demo["model"]["net"]["weights"] == "weights/demo-warmstart.pt"
        and scratch["model"]["net"]["weights"] is None
    )
    assert scratch["model"]["net"]["options"]["camera_correlation"] is False  # no correlation branch
    assert (scratch["model"]["optim"]["lr"], scratch["model"]["optim"]["appearance_lr"]) == (5e-4, 1e-3)
    assert differences(demo, scratch) == {
        "trainer.default_root_dir", "model.net.weights", "model.net.options.camera_correlation",
        "model.optim.lr", "model.optim.appearance_lr", "wandb.name",
    }  # fmt: skip


def test_warm_start_trains_the_demos_network_with_poses(parsed):
    demo = config_of(parsed, "conf/demo.yaml")
    warm = config_of(parsed, "conf/demo.yaml", "conf/warmstart.yaml")
    assert differences(demo["model"]["net"], warm["model"]["net"]) == {"weights"}  # the network the demo loads
    assert warm["model"]["cameras"] == "dataset" and warm["model"]["loss"]["pose_weight"] == 1.0
    assert warm["data"]["root"] == "outputs/warmstart/shards" and warm["trainer"]["max_steps"] == 8000


@pytest.mark.parametrize("name", ["baseline", "baseline_i2dc", "full", "i2dc_only", "no_gvsre", "no_wcm"])
def test_ablation_rows_change_the_appearance_and_the_schedule(parsed, name):
    config = config_of(parsed, "conf/re10k.yaml", f"conf/ablation/{name}.yaml")
    assert config["model"]["net"]["appearance"] == name and config["trainer"]["max_steps"] == 50000
    assert config["trainer"]["default_root_dir"] == f"outputs/ablation/{name}"


@pytest.mark.parametrize(
    ("files", "root"),
    [
        (("conf/re10k.yaml", "conf/eval/re10k_to_acid.yaml"), "outputs/shards/acid"),
        (("conf/re10k.yaml", "conf/acid.yaml", "conf/eval/acid_to_re10k.yaml"), "outputs/shards/re10k"),
    ],
)
def test_cross_dataset_evaluations_read_the_other_data_set(parsed, files, root):
    config = config_of(parsed, *files, command="test")
    assert config["data"]["root"] == root
    # With --ckpt_path the checkpoint's `model` section replaces the config's: an overlay's model keys would be
    # silently lost, so it has none; its results go to a run directory of their own.
    assert "model" not in yaml.safe_load((REPO / files[-1]).read_text())
    assert config["trainer"]["default_root_dir"].endswith(f"/eval/{root.rsplit('/', 1)[1]}")


def test_the_depth_range_is_the_models_alone(parsed):
    """One owner: model.net.near / far (the depth head's range); the data carry none."""
    expected = {"large": (1.0, 100.0), "tiny": (0.1, 10.0)}  # RealEstate10K / ACID; the synthetic rooms
    for line, config in parsed.items():
        net = config["model"]["net"]
        assert (net["near"], net["far"]) == expected[net["size"]], line
        assert "near" not in config["data"] and "far" not in config["data"], line
    model = NetConfig(**config_of(parsed, "conf/demo.yaml")["model"]["net"] | {"weights": None}).build()
    assert (model.cfg.near, model.cfg.far) == (0.1, 10.0)
    assert (model.depth_head.near, model.depth_head.far) == (0.1, 10.0)


def test_one_default_depth_range():
    assert (NetConfig().near, NetConfig().far) == (ModelConfig().near, ModelConfig().far)
    assert NetConfig().build().cfg.near == ModelConfig().near


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["--data.near", "1.0"], "--data.near"),
        (["--data.far=50"], "--data.far"),
        (["-c", "OLD"], "OLD sets data.near"),
    ],
)
def test_configs_that_set_the_removed_data_depth_range_fail_with_the_fix(tmp_path, args, names):
    old = tmp_path / "old.yaml"
    old.write_text("data:\n  root: somewhere\n  near: 1.0\n  far: 100.0\n")
    args = [str(old) if a == "OLD" else a for a in args]
    with pytest.raises(SystemExit) as info:
        cli.main(["fit", "-c", str(REPO / "conf/smoke.yaml"), *args, "--print_config"])
    message = str(info.value.code)
    assert message.startswith(f"aesplat fit: {names.replace('OLD', str(old))}")
    assert "model.net." in message and "\n" not in message


def test_configs_without_removed_keys_pass_the_check():
    assert removed_key_error(["fit", "-c", str(REPO / "conf/re10k.yaml"), "--model.net.near", "2"]) is None


def test_unknown_render_option_is_named_with_the_known_ones():
    with pytest.raises(ValueError, match=r"model.render.options: unknown key\(s\) \['tile_sise'\].*tile_size"):
        RasterizerConfig(options={"tile_sise": 8})
    assert RasterizerConfig(options={"tile_size": 16}).options.tile_size == 16


def test_demo_pool_is_the_demo_with_a_range_of_counts(parsed):
    demo = config_of(parsed, "conf/demo.yaml")
    pool = config_of(parsed, "conf/demo.yaml", "conf/demo_pool.yaml")
    assert demo["model"]["net"]["view_aggregation"] == "pool"  # the demo's head takes any count itself
    assert pool["data"]["num_context_views"] == [2, 4] and demo["data"]["num_context_views"] == 2
    assert pool["trainer"]["default_root_dir"] == "outputs/demo_pool/run"
    assert differences(demo, pool) == {"trainer.default_root_dir", "data.num_context_views", "wandb.name"}
    tested = config_of(parsed, "conf/demo.yaml", "conf/demo_pool.yaml", command="test")
    assert tested["data"]["num_context_views"] == 3
