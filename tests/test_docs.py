"""The README and the documentation pages: every `aesplat …` command they show parses, every `make` target they
name exists, and the configuration reference can be generated from the code.

Commands are taken from code blocks (fenced or indented) and inline code spans of README.md and docs/**/*.md.
`aesplat fit|validate|test` lines are parsed by the real LightningCLI with ``--print_config`` (nothing runs);
`aesplat predict|bench` lines by their own argument parsers. ``--ckpt_path FILE`` is dropped before parsing
(LightningCLI would read the checkpoint's hyper-parameters from the file), and lines that show a choice or an
elision (``fit|validate|test``, ``…``) are templates, not commands.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import re
import shlex
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
SUBCOMMANDS = ("fit", "validate", "test", "predict", "bench")


def _code_lines(text: str) -> list[str]:
    """Lines of fenced and indented code blocks, and inline code spans, continuation lines joined."""
    lines, fenced, previous_blank = [], False, True
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or (line.startswith("    ") and (previous_blank or (lines and lines[-1] is not None))):
            lines.append(line.strip())
        else:
            lines.append(None)
            # inline spans count when they are whole commands (a config or a checkpoint), not mentions
            spans = re.findall(r"`(aesplat [^`]+)`", line)
            lines.extend(s for s in spans if re.search(r" -c | --ckpt[ =]", s))
            lines.append(None)
        previous_blank = not line.strip()
    joined, current = [], ""
    for line in lines:
        if line is None:
            current = ""
            continue
        current += line
        if current.endswith("\\"):
            current = current[:-1] + " "
            continue
        joined.append(current)
        current = ""
    return joined


def _commands(text: str) -> list[str]:
    commands = []
    for line in _code_lines(text):
        line = line.removeprefix("$ ")
        match = re.match(r"^(?:[A-Z_]+=\S+\s+)*aesplat\s+(\S+)(.*)$", line)
        if not match or match.group(1) not in SUBCOMMANDS:
            continue
        command = match.group(0).split("  #")[0].split(" # ")[0].strip()
        if "…" in command or "..." in command or "|" in match.group(1):
            continue
        commands.append(command[command.index("aesplat") :])
    return commands


def documented_commands() -> list[tuple[str, str]]:
    found = {}
    for page in PAGES:
        for command in _commands(page.read_text()):
            found.setdefault(command, page.relative_to(REPO).as_posix())
    return sorted((page, command) for command, page in found.items())


def _argv(command: str) -> list[str]:
    argv = shlex.split(command.replace("[", " ").replace("]", " "))[1:]
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg == "--ckpt_path":
            skip = True
            continue
        if arg.startswith("--ckpt_path="):
            continue
        out.append(arg)
    return out


def _app_module(subcommand: str):
    if subcommand == "predict":
        return importlib.import_module("aesplat.predict")
    # `aesplat bench` lives in aesplat.tradeoffs (formerly aesplat.bench).
    name = "aesplat.tradeoffs" if importlib.util.find_spec("aesplat.tradeoffs") else "aesplat.bench"
    return importlib.import_module(name)


def test_the_docs_show_commands_of_every_kind():
    kinds = {command.split()[1] for _, command in documented_commands()}
    assert kinds == set(SUBCOMMANDS), kinds


@pytest.mark.parametrize(("page", "command"), documented_commands(), ids=lambda value: value[:60])
def test_documented_command_parses(page, command, monkeypatch):
    monkeypatch.chdir(REPO)
    monkeypatch.setenv("WANDB_MODE", "disabled")
    argv = _argv(command)
    if argv[0] in ("predict", "bench"):
        parser = _app_module(argv[0]).build_parser()
        parser.parse_args(argv[1:])  # argparse exits (SystemExit 2) on an unknown or malformed argument
        return
    from aesplat.cli import run_lightning

    monkeypatch.setattr("sys.argv", ["aesplat"])  # LightningCLI also looks at sys.argv (pytest's here)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), pytest.raises(SystemExit) as exit_info:
        run_lightning([*argv, "--print_config"])
    assert exit_info.value.code in (0, None), f"{page}: `{command}` does not parse"
    assert "model:" in printed.getvalue() and "data:" in printed.getvalue(), f"{page}: `{command}`"


def test_a_command_with_a_wrong_key_does_not_parse(monkeypatch):
    """The check above can fail: a misspelt key stops LightningCLI's parser."""
    from aesplat.cli import run_lightning

    monkeypatch.chdir(REPO)
    monkeypatch.setattr("sys.argv", ["aesplat"])
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        with pytest.raises(SystemExit) as exit_info:
            run_lightning(
                ["fit", "-c", "conf/smoke.yaml", "--model.optim.learning_rate", "1", "--print_config"]
            )
    assert exit_info.value.code not in (0, None)
    with pytest.raises(SystemExit):
        _app_module("bench").build_parser().parse_args(["--ckpt", "x.ckpt", "--no-such-option"])


def test_documented_make_targets_exist():
    makefile = (REPO / "Makefile").read_text()
    targets = set(re.findall(r"^([a-z][a-z0-9_-]*)\s*:", makefile, flags=re.MULTILINE))
    named = {}
    for page in PAGES:
        # `make X` in inline code, or a code line that starts with it
        for target in re.findall(r"(?:^\s*|`)make ([a-z][a-z0-9-]*)", page.read_text(), flags=re.MULTILINE):
            named.setdefault(target, page.relative_to(REPO).as_posix())
    missing = {target: page for target, page in named.items() if target not in targets}
    assert not missing, f"`make TARGET` in the docs with no such target in the Makefile: {missing}"
    assert {"demo", "test", "docs", "docs-serve"} <= named.keys()


def test_config_reference_covers_every_config_field():
    import dataclasses

    from aesplat.render import RenderSettings

    spec = importlib.util.spec_from_file_location("config_reference", REPO / "scripts" / "config_reference.py")
    reference = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reference)
    text = reference.markdown()
    sections = {name: rows for name, _, rows in reference.sections()}
    for field in dataclasses.fields(RenderSettings):
        assert f"| `{field.name}` |" in text
    assert [row[0] for row in sections["model.render.options"]] == [
        f.name for f in dataclasses.fields(RenderSettings)
    ]
    data_keys = [row[0] for row in sections["data"]]
    assert "batch_size" in data_keys and "root" in data_keys
    # The shipped configs' values appear beside the defaults: conf/demo.yaml trains 600 steps.
    demo_row = next(line for line in text.splitlines() if line.startswith("| `trainer.max_steps` |"))
    assert "`600`" in demo_row
