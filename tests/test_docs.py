"""The README and the documentation pages: every `aesplat …` command they show parses, every `make` target they
name exists, and the configuration reference can be generated from the code.

Commands are taken from code blocks (fenced or indented) and inline code spans of README.md and docs/**/*.md.
`aesplat fit|validate|test` lines are parsed by the parser of the real LightningCLI (nothing runs);
`aesplat predict|bench|view|export` lines and `python data_prep|benchmarks|scripts/NAME.py` lines by their own
argparse parsers. ``--ckpt_path FILE`` is dropped before parsing (LightningCLI would read the checkpoint's
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

from tests.helpers import REPO
from tests.script_loader import load_benchmark

PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
SUBCOMMANDS = ("fit", "validate", "test", "predict", "bench", "view", "export")
APPS = {  # the commands with an argparse parser of their own, by module
    "predict": "aesplat.predict",
    "bench": "aesplat.bench.command",  # accuracy against time
    "view": "aesplat.view.command",
    "export": "aesplat.export.command",
}


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
    return importlib.import_module(APPS[subcommand])


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
    monkeypatch.syspath_prepend(str((REPO / path).parent))  # as when it runs: its neighbours import by name
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
    from aesplat.data import DataModule
    from aesplat.lightning_cli import AESplatCLI, LightningParser
    from aesplat.train import AESplatModule

    captured = {}

    class Capture(AESplatCLI):
        def parse_arguments(self, parser, args):
            captured["parser"] = parser
            raise _Stop

    with pytest.raises(_Stop):
        Capture(AESplatModule, DataModule, args=["fit"], parser_kwargs={"parser_mode": "omegaconf"},
                parser_class=LightningParser, auto_configure_optimizers=False)  # fmt: skip
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
    if argv[0] in APPS:
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
    from aesplat.lightning_cli import run_lightning

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
    # The shipped configs' values appear beside the defaults, the paper's configs first (a wide table hides its
    # last columns): conf/re10k.yaml trains 400k steps, conf/demo.yaml 600.
    rows = [line for line in text.splitlines() if line.startswith("| `trainer.max_steps` |")]
    assert "`400000`" in rows[0] and "`600`" in rows[1]
    groups = [line for line in text.splitlines() if line.startswith("| key | `")]
    assert groups[0] == "| key | `re10k` | `acid` | default |" and all(g.count("|") <= 6 for g in groups)


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


# ---------------------------------------------------------------------------------------------------
# One source per figure (scripts/figures.py): a figure a page states agrees with the file its command wrote.


def _figures_module():
    spec = importlib.util.spec_from_file_location("docs_figures", REPO / "scripts" / "figures.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


@pytest.fixture()
def figures(monkeypatch):
    module = _figures_module()
    source = {"test": {"trained": {"psnr": 20.0512, "rot": 3.3049}, "gain": -0.384, "commit": "d2696ad",
                       "commit2": "1976cb4",
                       "wall_seconds": 298.4, "date": "2026-11-26T08:15:00+00:00", "scenes": 1536},
              "rows": [{"step": "0", "psnr": "19.5"}, {"step": "600", "psnr": "20.05"},
                       {"step": "600", "psnr": "21.0", "seed": "1"}],
              "requires": ["numpy>=1.26", "torch>=2.11", "kornia>=0.9"], "tiny": "5.0e-5"}  # fmt: skip
    monkeypatch.setitem(module.SOURCES, "t", lambda: source)
    return module


def _fig(key: str, text: str, spec: str = "") -> str:
    return f"<!-- fig t:{key}{' | ' + spec if spec else ''} -->{text}<!-- /fig -->"


@pytest.mark.parametrize(
    ("key", "text", "spec"),
    [("test.trained.psnr", "20.05", ""), ("test.trained.psnr", "20.1", ""), ("test.trained.psnr", "20", ""),
     ("test.gain", "−0.38", ""), ("test.gain", "-0.4", ""), ("test.scenes", "1,536", ""),
     ("test.scenes", "1,536", ",d"), ("test.trained.psnr", "+20.05", "+.2f"),
     ("test.wall_seconds", "4 min 58 s", "duration"), ("rows[1].step", "10 min", "duration"),
     ("test.date", "2026-11-26", "date"),
     ("test.commit", "d2696ad", ""), ("test.commit2", "1976cb4", ""),
     ("rows[step=600].psnr", "20.05", ""), ("rows[1].psnr", "20.05", ""),
     ("rows[step=600,seed=1].psnr", "21.0", ""), ("requires[torch]", "2.11", "floor"),
     ("test.trained.rot", "3.30", "")],
)  # fmt: skip
def test_a_figure_agrees_with_its_source(figures, key, text, spec):
    assert figures.problems(f"the demo scores {_fig(key, text, spec)} dB") == []


@pytest.mark.parametrize(
    ("key", "text", "spec"),
    [("test.trained.psnr", "20.06", ""), ("test.trained.psnr", "19.98", ""), ("test.gain", "0.38", ""),
     ("test.scenes", "1,535", ""), ("test.trained.psnr", "20.05", "+.2f"), ("test.wall_seconds", "2 min 37 s",
     "duration"), ("test.commit", "dd26b29", ""), ("test.commit2", "1976", ""),
     ("rows[step=0].psnr", "20.05", ""),
     ("requires[torch]", "2.13", "floor"), ("test.trained.rot", "3.31", "")],
)  # fmt: skip
def test_a_figure_that_disagrees_with_its_source_is_reported(figures, key, text, spec):
    found = figures.problems(f"line one\nthe demo scores {_fig(key, text, spec)} dB", "page.md")
    assert len(found) == 1 and found[0].startswith("page.md:2: the page says"), found


def test_a_figure_whose_source_or_key_is_missing_is_reported(figures):
    assert "no 'psnr'" in figures.problems(_fig("test.psnr", "20.05"))[0]
    assert "does not exist" in figures.problems("<!-- fig docs/no-such.json:a -->1<!-- /fig -->")[0]
    assert "no source named 'nosuch'" in figures.problems("<!-- fig nosuch:a -->1<!-- /fig -->")[0]
    assert "without a matching" in figures.problems("<!-- fig t:test.gain -->-0.38")[0]
    example = "Write `<!-- fig t:test.gain -->9<!-- /fig -->`, or:\n```\n<!-- fig t:x -->1<!-- /fig -->\n```"
    assert figures.problems(example) == [] and figures.strip(example) == example  # code shows, never checks


def test_markdown_tables_are_sources(figures, tmp_path, monkeypatch):
    page = tmp_path / "results.md"
    page.write_text("# Speed\n\n| run | seconds per step |\n| --- | ---: |\n| eager (`foreach`) | 0.453 |\n"
                    "| eager again | 0.442 |\n| **as shipped** | 0.333 (fused) |\n")  # fmt: skip
    monkeypatch.setattr(figures, "REPO", tmp_path)
    assert figures.lookup(figures.load("results.md"), "[run=eager].seconds per step") == "0.453"
    assert figures.problems("<!-- fig results.md:[run=as shipped].seconds per step -->0.333<!-- /fig -->") == []
    assert figures.problems("<!-- fig results.md:[run=eager again].seconds per step -->0.453<!-- /fig -->")


def test_write_puts_each_sources_value_into_the_page(figures):
    def page(psnr: str, gain: str, wall: str) -> str:
        wall = _fig("test.wall_seconds", wall, "duration")
        return f"PSNR {_fig('test.trained.psnr', psnr)} dB, gain {_fig('test.gain', gain)}, {wall}"

    new = figures.rewrite(page("19.98", "−0.41", "2 min"))
    assert new == page("20.05", "−0.38", "4 min 58 s")
    assert figures.rewrite(page("20.1", "-0.4", "4 min 58 s")) == page("20.1", "-0.4", "4 min 58 s")  # agree
    assert figures.rewrite(_fig("tiny", "5e-5")) == _fig("tiny", "5e-5")
    assert figures.rewrite(_fig("tiny", "7e-5")) == _fig("tiny", "5e-5")  # the page's notation
    assert figures.problems(new) == [] and figures.strip(new) == "PSNR 20.05 dB, gain −0.38, 4 min 58 s"


def test_every_figure_of_the_readme_and_the_pages_agrees_with_its_source():
    figures = _figures_module()
    found = [
        line for page in PAGES for line in figures.problems(page.read_text(), page.relative_to(REPO).as_posix())
    ]
    assert not found, "\n".join(found)


def test_the_docs_build_fails_on_a_figure_that_disagrees_and_shows_the_figure_without_its_comments():
    from types import SimpleNamespace

    spec = importlib.util.spec_from_file_location("mkdocs_hooks_figures", REPO / "scripts" / "mkdocs_hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    page = SimpleNamespace(file=SimpleNamespace(src_uri="index.md"))
    good = "floor <!-- fig pyproject:project.dependencies[torch] | floor -->{}<!-- /fig -->"
    floor = hooks._figures.lookup(hooks._figures.load("pyproject"), "project.dependencies[torch]")
    right = floor.removeprefix(">=").split(",")[0]
    assert hooks.on_page_markdown(good.format(right), page, None, None) == f"floor {right}"
    with pytest.raises(ValueError, match="disagree"):
        hooks.on_page_markdown(good.format(right + ".9"), page, None, None)


def test_the_paper_page_deltas_are_the_papers_rows_minus_full():
    """docs/paper.md copies the paper's ablation table; its Δ column is each row's PSNR less `full`'s."""
    rows = [r for r in _figures_module()._markdown_tables(REPO / "docs" / "paper.md") if "paper: Δ" in r]
    full = float(next(r["paper: PSNR"] for r in rows if r["row"] == "full"))
    deltas = {r["row"]: r["paper: Δ"] for r in rows if r["row"] != "full"}
    assert len(deltas) == 5
    for row, delta in deltas.items():
        psnr = float(next(r["paper: PSNR"] for r in rows if r["row"] == row))
        assert float(delta.replace("−", "-")) == pytest.approx(psnr - full, abs=5e-4), row


def test_a_source_records_when_where_and_under_what_load_it_was_measured():
    import subprocess

    record = load_benchmark("common").provenance([0.5, 0.4, 0.3])
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    assert record["commit"] == head.stdout.strip() and isinstance(record["modified"], bool)
    assert record["load"]["start"] == [0.5, 0.4, 0.3] and len(record["load"]["end"]) == 3
    assert record["machine"]["cores"] >= 1 and record["date"].endswith("+00:00")


# Pages a newcomer reads first: every measured figure on them (a number with a unit of measure) is written
# between figure comments, so it is checked against its source. Code blocks and inline code are not prose.
OVERVIEW_PAGES = ["README.md", "docs/index.md", "docs/getting-started.md", "docs/results/index.md"]
MEASURED = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)?\s?(?:dB|°|ms|GiB|MiB|min|s/step|samples/s|×)(?!\w)")


@pytest.mark.parametrize("name", OVERVIEW_PAGES)
def test_overview_pages_state_measured_figures_only_from_their_sources(name):
    figures = _figures_module()
    text = (REPO / name).read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)
    text = figures.MARKER.sub("", text)  # a checked figure and its unit
    text = re.sub(r"`[^`]*`|<!--.*?-->|\([^()]*\.(?:png|md)[^()]*\)", "", text, flags=re.DOTALL)
    unsourced = [
        line.strip() for line in text.splitlines() if MEASURED.search(line) and not line.startswith("    ")
    ]
    assert not unsourced, f"{name}: measured figures not read from a source:\n" + "\n".join(unsourced)


# A code block wider than this scrolls sideways on a 1280-pixel screen (the site's theme shows about 82
# characters of code there): wrap long commands with `\` and put long comments on lines of their own.
CODE_WIDTH = 80


def _displayed_code_lines(text: str) -> list[tuple[int, str]]:
    """(line number, text as shown) of every line of a fenced or top-level indented code block."""
    found, fenced, indent, previous_blank, in_block = [], False, 0, True, False
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.lstrip()
        if stripped.startswith("```"):
            fenced, indent, in_block = not fenced, len(line) - len(stripped), False
        elif fenced:
            found.append((number, line[indent:]))
        elif line.startswith("    ") and (previous_blank or in_block):
            if in_block or not re.match(r"\s*(?:[-*]|\d+\.)\s", line):
                found.append((number, line[4:]))
                in_block = True
        elif line.strip():
            in_block = False
        previous_blank = not line.strip()
    return found


def test_code_blocks_fit_the_page():
    wide = [f"{page.relative_to(REPO)}:{number}: {len(shown)} characters"
            for page in PAGES for number, shown in _displayed_code_lines(page.read_text())
            if len(shown.rstrip()) > CODE_WIDTH]  # fmt: skip
    assert not wide, "code lines wider than the page (wrap with `\\`):\n" + "\n".join(wide)
    assert _displayed_code_lines("text\n\n    aesplat fit \\\n        -c x.yaml\n```\na\n```\n") == [
        (3, "aesplat fit \\"), (4, "    -c x.yaml"), (6, "a")]  # fmt: skip


def test_the_pages_speak_of_the_project_not_of_how_it_was_made():
    """A figure says its date, commit, machine and load; never who measured it or who else used the machine."""
    making = re.compile(r"\b(?:sessions?|engineers?|coordinator|integrator|other helpers)\b", re.IGNORECASE)
    pages = [*PAGES, REPO / "CHANGELOG.md", REPO / "benchmarks" / "RESULTS.md"]
    found = [f"{page.relative_to(REPO)}:{number}: {line.strip()[:80]}"
             for page in pages for number, line in enumerate(page.read_text().splitlines(), 1)
             if making.search(line)]  # fmt: skip
    assert not found, "\n".join(found)


# The paper's names a reader meets on the pages, each defined once on the method page (docs/design.md#ANCHOR).
TERMS = {
    "I2DC": "i2dc",
    "GVSRE": "gvsre",
    "WCM": "wcm",
    "DPT": "dpt",
    "alternating attention": "alternating-attention",
}


def _prose(text: str) -> str:
    """The page with code blocks, indented code and inline code blanked out (same length)."""
    blank = lambda m: re.sub(r"[^\n]", " ", m.group(0))  # noqa: E731
    text = re.sub(r"```.*?```", blank, text, flags=re.DOTALL)
    text = re.sub(r"(?m)^    .*$", blank, text)
    return re.sub(r"`[^`\n]*`", blank, text)


def test_each_term_of_the_paper_links_the_method_page_where_a_page_first_uses_it():
    unexplained = []
    for page in PAGES:
        name = page.relative_to(REPO).as_posix()
        if name == "docs/design.md" or "/curves/" in name or "/ablation/" in name or "/pose_probe/" in name:
            continue  # the definitions themselves, and the files benchmarks write
        text = page.read_text()
        prose = _prose(text)
        for term, anchor in TERMS.items():
            found = re.search(rf"(?<![\w-]){re.escape(term)}(?![\w-])", prose)
            if found is None:
                continue
            linked = (
                text[found.start() - 1] == "["
                and f"design.md#{anchor})" in text[found.end() : found.end() + 60]
            )
            if not linked:
                unexplained.append(f"{name}:{text.count(chr(10), 0, found.start()) + 1}: {term}")
    assert not unexplained, "first use without a link to its definition on the method page:\n" + "\n".join(
        unexplained
    )
    assert all(f"{{ #{anchor} }}" in (REPO / "docs" / "design.md").read_text() for anchor in TERMS.values())


# The widest tables that fit the page at 1280 px have 7 columns; the 8- to 11-column ones hid their last
# columns (split a wider table, the key columns first in each part).
TABLE_COLUMNS = 7


def test_tables_fit_the_page():
    wide = []
    for page in PAGES:
        header = None
        for number, line in enumerate(page.read_text().splitlines(), 1):
            stripped = line.strip()
            if not (stripped.startswith("|") and stripped.endswith("|")):
                header = None
            elif header is None:
                header = len(re.split(r"(?<!\\)\|", stripped[1:-1]))
                if header > TABLE_COLUMNS:
                    wide.append(f"{page.relative_to(REPO)}:{number}: {header} columns")
    assert not wide, "tables wider than the page:\n" + "\n".join(wide)
