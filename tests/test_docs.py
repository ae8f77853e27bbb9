"""The README and the documentation pages: every `aesplat …` command they show parses, every `make` target they
name exists, and the configuration reference can be generated from the code.

Commands are taken from code blocks (fenced or indented) and inline code spans of README.md and docs/**/*.md.
`aesplat fit|validate|test` lines are parsed by the parser of the real LightningCLI (nothing runs);
`aesplat predict|bench` lines and `python data_prep|benchmarks|scripts/NAME.py` lines by their own argparse
parsers. ``--ckpt_path FILE`` is dropped before parsing (LightningCLI would read the checkpoint's
hyper-parameters from the file), so is ``--print_config`` (it prints and exits), and lines that show a choice
or an elision (``fit|validate|test``, ``…``) are templates, not commands.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import inspect
import io
import re
import shlex
import sys
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
        if arg.startswith("--ckpt_path=") or arg == "--print_config":  # the latter would print and exit
            continue
        out.append(arg)
    return out


def _app_module(subcommand: str):
    if subcommand == "predict":
        return importlib.import_module("aesplat.predict")
    return importlib.import_module("aesplat.bench")  # `aesplat bench`: accuracy against time


def _script_commands(text: str) -> list[str]:
    """`python data_prep|benchmarks|scripts/NAME.py …` lines of code blocks (environment prefixes dropped)."""
    commands = []
    for line in _code_lines(text):
        match = re.match(
            r"^(?:[A-Z_]+=\S+\s+)*(?:\.venv/bin/)?python\s+((?:data_prep|benchmarks|scripts)/\w+\.py)(.*)$",
            line,
        )
        if not match:
            continue
        command = (match.group(1) + match.group(2)).split("  #")[0].split(" # ")[0].strip()
        if "…" in command or "..." in command or "|" in command:
            continue
        commands.append(command)
    return commands


def documented_script_commands() -> list[tuple[str, str]]:
    found = {}
    for page in PAGES:
        for command in _script_commands(page.read_text()):
            found.setdefault(command, page.relative_to(REPO).as_posix())
    return sorted((page, command) for command, page in found.items())


class _Parsed(Exception):
    """Raised in place of running a script once its arguments parsed."""


@pytest.mark.parametrize(("page", "command"), documented_script_commands(), ids=lambda value: value[:60])
def test_documented_script_command_parses(page, command, monkeypatch):
    """The script's own argparse parser accepts the documented arguments; the script itself does not run."""
    import argparse

    path, *args = shlex.split(command.replace("[", " ").replace("]", " "))
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(parser, argv=None, namespace=None):
        original(parser, argv, namespace)  # exits with status 2 on an unknown or malformed argument
        raise _Parsed

    monkeypatch.chdir(REPO)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    monkeypatch.setattr("sys.argv", [path, *args])
    spec = importlib.util.spec_from_file_location(f"documented_{Path(path).stem}", REPO / path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses in the script look their module up
    spec.loader.exec_module(module)
    takes_argv = bool(inspect.signature(module.main).parameters)
    with pytest.raises(_Parsed):
        module.main(args) if takes_argv else module.main()


def test_the_docs_show_commands_of_every_kind():
    kinds = {command.split()[1] for _, command in documented_commands()}
    assert kinds == set(SUBCOMMANDS), kinds


class _Stop(Exception):
    """Raised in place of parsing, once LightningCLI has built its parser."""


@pytest.fixture(scope="module")
def lightning_parser():
    """The parser `aesplat fit|validate|test` uses, built once (the same class and options as the command)."""
    from aesplat.cli import _lightning_cli

    cli_class, module_class, data_class, parser_class, _ = _lightning_cli()
    captured = {}

    class Capture(cli_class):
        def parse_arguments(self, parser, args):
            captured["parser"] = parser
            raise _Stop

    with pytest.raises(_Stop):
        Capture(module_class, data_class, args=["fit"], parser_kwargs={"parser_mode": "omegaconf"},
                parser_class=parser_class, auto_configure_optimizers=False)  # fmt: skip
    return captured["parser"]


def _config_files(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, arg in enumerate(argv[:-1]) if arg in ("-c", "--config")]


def _bases(overlay: str) -> list[str]:
    """The configs an overlay is layered on, as its own header's usage lines show (empty for a full config)."""
    for line in (REPO / overlay).read_text().splitlines():
        if not line.startswith("#"):
            break
        if "aesplat " not in line:
            continue
        files = _config_files(shlex.split(line.lstrip("# ").split("  #")[0]))
        if overlay in files:
            return files[: files.index(overlay)]
    return []


@pytest.mark.parametrize(("page", "command"), documented_commands(), ids=lambda value: value[:60])
def test_documented_command_parses(page, command, monkeypatch, lightning_parser):
    monkeypatch.chdir(REPO)
    argv = _argv(command)
    files = _config_files(argv)
    for i, config in enumerate(
        files
    ):  # an overlay alone parses, but runs the defaults: its base must come first
        missing = [base for base in _bases(config) if base not in files[:i]]
        assert not missing, f"{page}: `{command}` layers {config} without {missing} before it"
    if argv[0] in ("predict", "bench"):
        parser = _app_module(argv[0]).build_parser()
        parser.parse_args(argv[1:])  # argparse exits (SystemExit 2) on an unknown or malformed argument
        return
    with contextlib.redirect_stderr(io.StringIO()) as errors:
        try:
            config = lightning_parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"{page}: `{command}` does not parse: {errors.getvalue().strip()}")
    assert config.subcommand == argv[0]
    assert config[argv[0]].data.batch_size >= 1


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


def test_readme_stays_an_entry_point():
    """At most 250 lines, the two commands first: everything else belongs on a docs page."""
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; move detail to a page under docs/"
    commands = [line.split("#")[0].strip() for line in lines if line.startswith("make ")]
    assert commands[:2] == ["make demo", "make test"], commands[:2]


def test_the_docs_build_puts_the_reference_into_the_configuration_page():
    """scripts/mkdocs_hooks.py replaces the marker of docs/configuration.md, and refuses a page without it."""
    from types import SimpleNamespace

    spec = importlib.util.spec_from_file_location("mkdocs_hooks", REPO / "scripts" / "mkdocs_hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    page = SimpleNamespace(file=SimpleNamespace(src_uri="configuration.md"))
    source = (REPO / "docs" / "configuration.md").read_text()
    built = hooks.on_page_markdown(source, page, None, None)
    assert hooks.MARKER not in built and "### `model.optim`" in built
    other = SimpleNamespace(file=SimpleNamespace(src_uri="training.md"))
    assert hooks.on_page_markdown("text", other, None, None) == "text"
    with pytest.raises(ValueError, match="config-reference"):
        hooks.on_page_markdown(source.replace(hooks.MARKER, ""), page, None, None)
