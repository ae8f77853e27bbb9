"""The configuration reference: every key of the config sections aesplat defines, from the code itself.

    python scripts/config_reference.py            # prints the Markdown the docs site shows on configuration.md

The tables are read from the config dataclasses (``model.net``, ``model.loss``, ``model.optim``,
``model.render``, ``model.eval``, ``wandb``, ``distributed``), the render settings (``model.render.options``)
and the DataModule's arguments (``data``): key, type, default, meaning (the field's comment or docstring line),
and the value each shipped ``conf/*.yaml`` gives it. The docs build (``scripts/mkdocs_hooks.py``) inserts it,
so the page cannot drift from the code.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import sys
import typing
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]


def _field_comments(cls: type) -> dict[str, str]:
    """Trailing ``# comment`` of each ``name: type = default`` line, or the comment lines just above it."""
    comments: dict[str, str] = {}
    above: list[str] = []
    for line in inspect.getsource(cls).splitlines()[1:]:
        stripped = line.strip()
        if stripped.startswith("#"):
            above.append(stripped.lstrip("#").strip())
            continue
        match = re.match(r"^\s+(\w+)\s*:[^#]*?(?:#\s*(.*))?$", line)
        if match and not stripped.startswith(("def ", "return", '"""')):
            text = match.group(2) or " ".join(above)
            comments.setdefault(match.group(1), text.strip())
        above = []
    return comments


def _docstring_entries(doc: str) -> dict[str, str]:
    """``name: text`` (Google ``Args:``) or ``name   text`` (aligned table) entries of a docstring."""
    entries: dict[str, str] = {}
    current: list[str] = []
    for line in inspect.cleandoc(doc or "").splitlines():
        match = re.match(r"^\s*([\w, /]+?)(?::\s+|\s{2,})(\S.*)$", line)
        names = match and [n for n in re.split(r"[,/ ]+", match.group(1)) if n]
        if match and names and all(re.fullmatch(r"[a-z_][a-z0-9_]*", n) for n in names):
            current = names
            for name in names:
                entries[name] = match.group(2).strip()
        elif current and line.startswith((" ", "\t")) and line.strip():
            for name in current:
                entries[name] += " " + line.strip()
        else:
            current = []
    return entries


def _type_name(annotation: Any) -> str:
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    return str(text).replace("typing.", "").replace("NoneType", "None")


def _default(value: Any) -> str:
    if value is dataclasses.MISSING or value is inspect.Parameter.empty:
        return "required"
    if dataclasses.is_dataclass(value):  # a typed section of its own, listed below
        return "see below"
    if isinstance(value, tuple):
        value = list(value)
    return yaml.safe_dump(value, default_flow_style=True, width=1000).strip().removesuffix("...").strip()


# Meanings of fields whose line in the code carries no comment (kept short; the code is the reference).
UNCOMMENTED = {
    "NetConfig.size": "size preset: tiny (about 2 M parameters, CPU), base (ViT-B/14), large (VGGT's shape)",
    "NetConfig.sh_degree": "SH degree of every Gaussian's colour (i2dc_only uses 0)",
    "NetConfig.near": "the depth head's range: nearest depth",
    "NetConfig.far": "the depth head's range: farthest depth",
    "RasterizerConfig.background": "RGB in [0, 1] behind the Gaussians",
}


def _rows_of_dataclass(cls: type) -> list[tuple[str, str, str, str]]:
    comments = {
        **{k.split(".", 1)[1]: v for k, v in UNCOMMENTED.items() if k.startswith(f"{cls.__name__}.")},
        **{k: v for k, v in _field_comments(cls).items() if v},
    }
    documented = _docstring_entries(cls.__doc__ or "")
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        meaning = comments.get(f.name) or documented.get(f.name, "")
        rows.append((f.name, _type_name(hints.get(f.name, f.type)), _default(default), meaning))
    return rows


def _rows_of_signature(func: Any, doc: str) -> list[tuple[str, str, str, str]]:
    documented = _docstring_entries(doc.split("Args:", 1)[-1])
    hints = typing.get_type_hints(func)
    rows = []
    for name, p in inspect.signature(func).parameters.items():
        if name == "self":
            continue
        rows.append(
            (name, _type_name(hints.get(name, p.annotation)), _default(p.default), documented.get(name, ""))
        )
    return rows


def sections() -> list[tuple[str, str, list[tuple[str, str, str, str]]]]:
    """(dotted section, what it is, rows of (key, type, default, meaning)), in the order a config lists them."""
    from aesplat.data import DataModule
    from aesplat.lightning_cli import DistributedConfig, WandbConfig
    from aesplat.model import NetOptions
    from aesplat.render import RenderSettings
    from aesplat.train import AESplatModule

    hints = typing.get_type_hints(AESplatModule.__init__)

    def config_class(name: str) -> type:
        (cls,) = [a for a in typing.get_args(hints[name]) if dataclasses.is_dataclass(a)] or [hints[name]]
        return cls

    cameras = inspect.signature(AESplatModule.__init__).parameters["cameras"].default
    model_rows = [
        ("cameras", "str", _default(cameras), "predicted (the camera head's: the method) or dataset (posed)"),
    ]
    return [
        ("model", "the LightningModule's own argument", model_rows),
        ("model.net", "the network: the arguments of `build_model`", _rows_of_dataclass(config_class("net"))),
        (
            "model.net.options",
            "the other `build_model` keywords (`NetOptions`; null keeps the size preset's value)",
            _rows_of_dataclass(NetOptions),
        ),
        ("model.loss", "loss weights and training-only levers", _rows_of_dataclass(config_class("loss"))),
        (
            "model.optim",
            "AdamW, the schedule and the skipped-step guard",
            _rows_of_dataclass(config_class("optim")),
        ),
        (
            "model.render",
            "the rasterizer used in training and evaluation",
            _rows_of_dataclass(config_class("render")),
        ),
        ("model.render.options", "rasterizer settings (`RenderSettings`)", _rows_of_dataclass(RenderSettings)),
        ("model.eval", "what `aesplat test` writes and logs", _rows_of_dataclass(config_class("eval"))),
        ("data", "the DataModule", _rows_of_signature(DataModule.__init__, DataModule.__doc__ or "")),
        ("wandb", "Weights & Biases", _rows_of_dataclass(WandbConfig)),
        ("distributed", "multi-process (DDP) training", _rows_of_dataclass(DistributedConfig)),
    ]


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(tree, dict):
        return {prefix: tree}
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        dotted = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict) and not (dotted.endswith(".options") and prefix.startswith("model")):
            flat.update(_flatten(value, dotted))
        else:
            flat[dotted] = value
    return flat


def shipped_values(conf_dir: Path = REPO / "conf") -> dict[str, dict[str, Any]]:
    """dotted key -> {config file (relative to conf/): value} over every shipped YAML file."""
    values: dict[str, dict[str, Any]] = {}
    for path in sorted(conf_dir.rglob("*.yaml")):
        flat = _flatten(yaml.safe_load(path.read_text()) or {})
        for key, value in flat.items():
            values.setdefault(key, {})[path.relative_to(conf_dir).as_posix()] = value
    return values


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


# The complete configs, in tables of a few columns each (a wide table hides its last columns), the paper's
# first; overlays (layered on one of them with a second -c) are listed apart.
CONFIG_GROUPS = (
    ("The paper's settings (GPU)", ("re10k", "acid")),
    ("The CPU demo and its warm start", ("demo", "demo_from_scratch", "warmstart")),
    ("The tests and the appearance ablation (CPU)", ("smoke", "appearance_ablation")),
)
MAIN_CONFIGS = tuple(name for _, names in CONFIG_GROUPS for name in names)


def _shipped_markdown(defaults: dict[str, str]) -> list[str]:
    shipped = shipped_values()
    out = [
        "### What the shipped configs set",
        "",
        "Every key a file in `conf/` sets, with its value where it differs from the default above (blank: the"
        " default, or not set). `trainer`, `checkpoint` and `last_checkpoint` keys are Lightning's.",
        "",
    ]
    for title, group in CONFIG_GROUPS:
        columns = [c for c in group if (REPO / "conf" / f"{c}.yaml").exists()]
        rows = []
        for key in sorted(shipped):
            default = defaults.get(key, "")
            cells = []
            for c in columns:
                value = shipped[key].get(f"{c}.yaml", None)
                shown = "" if value is None and f"{c}.yaml" not in shipped[key] else _default(value)
                cells.append(f"`{_cell(shown)}`" if shown and shown != default else "")
            if any(cells):
                shown_default = f"`{_cell(default)}`" if default else "(Lightning's)"
                rows.append(f"| `{key}` | " + " | ".join(cells) + f" | {shown_default} |")
        out += [f"#### {title}", "", "| key | " + " | ".join(f"`{c}`" for c in columns) + " | default |",
                "| --- | " + " | ".join("---" for _ in columns) + " | --- |", *rows, ""]  # fmt: skip
    out += ["Overlays, each layered on a complete config with a second `-c`:", ""]
    main = {f"{c}.yaml" for c in MAIN_CONFIGS}
    overlays = sorted({name for per in shipped.values() for name in per} - main)
    for name in overlays:
        sets = ", ".join(f"`{k}: {_cell(_default(v[name]))}`" for k, v in sorted(shipped.items()) if name in v)
        out.append(f"- `conf/{name}`: {sets}")
    return out + [""]


def markdown() -> str:
    out = []
    defaults: dict[str, str] = {}
    for section, what, rows in sections():
        out += [f"### `{section}`", "", f"{what[0].upper()}{what[1:]}.", ""]
        out += ["| key | type | default | meaning |", "| --- | --- | --- | --- |"]
        for key, type_name, default, meaning in rows:
            defaults[f"{section}.{key}"] = default
            shown_type = type_name.replace(" | ", " or ")  # a pipe inside a code span would show its escape
            out.append(f"| `{key}` | `{shown_type}` | `{_cell(default)}` | {_cell(meaning)} |")
        out.append("")
    return "\n".join(out + _shipped_markdown(defaults))


if __name__ == "__main__":
    sys.stdout.write(markdown())
