"""The documentation says what is: its links lead somewhere, the files it names exist, its Python
compiles (and the README's is part of a tested example), its `esiaf` command lines are ones the
command takes, and docs/configuration.md is what the settings give.

Checked files: README.md, CONTRIBUTING.md, CHANGELOG.md, docs/*.md and every service's README.
A relative link must name an existing file, and its ``#anchor`` a heading of that file (GitHub's
anchors: lower case, punctuation dropped, spaces as hyphens); a file path in the text
(`esiaf_services/vad/service.py`) must exist. The last tests show that each check
does find a broken link, a bad block and an unknown option, so a pass above means something.
"""
from __future__ import annotations

import contextlib
import io
import re
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import pytest

from esiaf.keys import main as keys_main
from esiaf.tools import cli_args, docgen, evaluation, mcap_diff, mcap_record
from esiaf.tools.testing import REPO

DOCS = sorted([REPO / "README.md", REPO / "CONTRIBUTING.md", REPO / "CHANGELOG.md",
               *(REPO / "docs").glob("*.md"), *(REPO / "esiaf_services").glob("*/README.md")])
FENCE = re.compile(r"^(```+|~~~+)\s*(\S*)[^\n]*\n(.*?)^\1\s*$", re.M | re.S)
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1", re.S)
SHELL_BLOCKS = {"", "sh", "bash", "shell", "console", "text"}
# a file of the repository named in the text (`esiaf_services/vad/service.py`), not only linked
NAMED_FILE = re.compile(r"(?<![\w/.-])((?:esiaf|esiaf_services|bench|tests|docs|scripts|docker|examples|proto)/"
                        r"[\w./-]*\.(?:py|md|ya?ml|sh|proto|toml|json|gram))\b")
COMMAND = re.compile(r"(?:^|(?<=[\s/(]))esiaf[ \t]+(\S[^\n]*)")
# what may stand before `esiaf` where it is the command (not `docker stack rm esiaf`): nothing, a
# shell operator, `python -m`, a path to it, variables set for it
COMMAND_START = re.compile(r"(?:^|.*(?:&&|\|\||;|\$|\(|`)|.*\bpython3? -m)\s*(?:[A-Z_][A-Z0-9_]*=\S*\s+)*\S*/?$")


def name(path: Path) -> str:
    return str(path.relative_to(REPO))


def prose(text: str) -> str:
    """The text without its fenced blocks and inline code: where links are links."""
    return INLINE_CODE.sub(" ", FENCE.sub("\n", text))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found: set[str] = set()
    counts: dict[str, int] = {}
    for line in FENCE.sub("\n", path.read_text()).splitlines():
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            base = slug(match.group(1))
            count = counts.get(base, 0)
            counts[base] = count + 1
            found.add(base if count == 0 else f"{base}-{count}")
    return found


def broken_links(path: Path) -> list[str]:
    """Every relative link of ``path`` whose file or anchor does not exist."""
    broken = []
    for target in LINK.findall(prose(path.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path
        if not resolved.exists():
            broken.append(f"{target}: no file {resolved}")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target}: no heading with the anchor #{anchor} in {resolved.name}")
    return broken


def missing_files(path: Path) -> list[str]:
    """Files of the repository the text names (from its root, or from the page's folder) that do
    not exist: a module moved or renamed since the text was written."""
    return sorted({name for name in NAMED_FILE.findall(path.read_text())
                   if not (REPO / name).exists() and not (path.parent / name).exists()})


def python_blocks(path: Path) -> Iterator[tuple[int, str]]:
    text = path.read_text()
    for match in FENCE.finditer(text):
        if match.group(2).lower() in ("python", "py"):
            yield text[:match.start()].count("\n") + 2, match.group(3)


def command_lines(path: Path) -> Iterator[str]:
    """What follows ``esiaf`` in each command shown: in shell blocks and in inline code."""
    text = path.read_text()
    blocks = [m.group(3) for m in FENCE.finditer(text) if m.group(2).lower() in SHELL_BLOCKS]
    spans = [" ".join(m.group(2).split()) for m in INLINE_CODE.finditer(FENCE.sub("\n", text))]
    for place in [*blocks, *spans]:
        for line in re.sub(r"\\\n\s*", " ", place).splitlines():  # continued lines joined
            for match in COMMAND.finditer(line):
                prefix = line[:match.start()]
                if COMMAND_START.match(prefix) and (not prefix or prefix[-1] in " \t/(`$;&|"):
                    yield match.group(1)


def words(command: str) -> list[str]:
    """The arguments of a command line as the shell would pass them; placeholders left out."""
    command = re.split(r"\s#\s|\s#$|&&|\|\||[|;>)`]", command)[0]
    try:
        tokens = shlex.split(command)
    except ValueError:
        tokens = command.split()
    kept: list[str] = []
    for token in tokens:
        token = token.strip("[]")
        if token and token not in ("...", "…") and "<" not in token:
            kept.append(token)
        elif kept and kept[-1].startswith("-"):  # an option's value left open: any value
            kept.append("X")
    return kept


def command_problem(command: str) -> str | None:
    """Why ``esiaf <command>`` is not a command line the esiaf command takes, or None."""
    argv = words(command)
    if not argv:
        return None
    if argv[0] not in ("run", "eval", "keys", "wyoming", "record", "mcap"):
        return f"esiaf has no subcommand {argv[0]!r} (run, eval, keys, wyoming, record, mcap)"
    problem = parse_problem(argv[0], argv[1:])
    if problem and argv[-1].startswith("--"):  # an option named in prose, its value left out
        problem = parse_problem(argv[0], [*argv[1:], "X"]) and problem
    return problem


def parse_problem(subcommand: str, args: list[str]) -> str | None:
    """What the esiaf command's argument parser says of ``esiaf <subcommand> <args>``, or None."""
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            if subcommand == "run":
                if not {"--input", "--mic"} & {a.split("=")[0] for a in args}:
                    args = ["--input", "speech.wav", *args]  # a fragment that names options only
                cli_args.parse_args(["run", *args])
            elif subcommand == "wyoming":
                cli_args.parse_args(["wyoming", *args])
            elif subcommand == "eval" and args:
                _, rest = evaluation.parse_args(args)
                if rest:
                    cli_args.parse_args(["run", "--input", "speech.wav", *rest])
            elif subcommand == "record":  # a fragment without --out names the command or its options only
                mcap_record.parse_args(args if "--out" in args else ["--out", "X.mcap", *args])
            elif subcommand == "mcap" and args[1:]:  # `esiaf mcap diff` named in prose: the command only
                mcap_diff.parse_args(args)
            elif subcommand == "keys":
                help_text = io.StringIO()
                with contextlib.suppress(SystemExit), contextlib.redirect_stdout(help_text):
                    keys_main(["--help"])
                options = set(re.findall(r"--[a-z][a-z-]*", help_text.getvalue()))
                unknown = [a for a in args if a.startswith("--") and a.split("=")[0] not in options]
                if unknown:
                    return f"esiaf keys has no option {', '.join(unknown)}"
    except SystemExit as exc:
        if exc.code in (0, None):  # --help
            return None
        return (stderr.getvalue().strip().splitlines() or [f"exit {exc.code}"])[-1]
    return None


@pytest.mark.parametrize("path", DOCS, ids=name)
def test_relative_links_resolve(path):
    assert broken_links(path) == [], f"{name(path)} has broken links"


@pytest.mark.parametrize("path", DOCS, ids=name)
def test_named_files_exist(path):
    assert missing_files(path) == [], f"{name(path)} names files that do not exist"


@pytest.mark.parametrize("path", DOCS, ids=name)
def test_python_blocks_compile(path):
    for line, code in python_blocks(path):
        try:
            compile(code, f"{name(path)}:{line}", "exec")
        except SyntaxError as exc:
            pytest.fail(f"{name(path)}, the block at line {line}: {exc}")


@pytest.mark.parametrize("path", DOCS, ids=name)
def test_esiaf_commands_are_real(path):
    problems = [f"esiaf {command}: {problem}" for command in command_lines(path)
                if (problem := command_problem(command))]
    assert problems == [], f"{name(path)} shows command lines esiaf does not take"


def test_the_readme_shows_tested_code():
    """The README's Python is part of a file in examples/, which tests run
    (tests/test_example_analysers.py, tests/test_readme_component.py)."""
    examples = [p.read_text() for p in (REPO / "examples").rglob("*.py")]
    for line, code in python_blocks(REPO / "README.md"):
        assert any(code.strip("\n") in example for example in examples), \
            f"README.md, the block at line {line}, is not an excerpt of a file in examples/"


def test_configuration_page_is_current():
    assert docgen.OUTPUT.read_text() == docgen.render(), \
        "docs/configuration.md is not what the settings models give: run python -m esiaf.tools.docgen"


def test_the_configuration_page_names_old_spellings():
    class Renamed(docgen.ComponentSettings):
        renamed: ClassVar[dict[str, str]] = {"nbest": "n_best"}
        n_best: int = 5  # hypotheses per segment

    text = "\n".join(docgen.section("x", "x", Renamed, ["n_best"]))
    assert "| `n_best` | int | `5` | `ESIAF_X_N_BEST` | hypotheses per segment |" in text
    assert "`nbest` (now `n_best`)" in text


def test_the_checks_find_what_is_wrong(tmp_path):
    (tmp_path / "there.md").write_text("# A heading, with `code`\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](there.md#a-heading-with-code) [gone](missing.md) [bad anchor](there.md#nothing)\n"
                    "[web](https://example.org/x) `[not a link](nowhere.md)`\n"
                    "`esiaf/tools/docgen.py` and `esiaf_services/orchestrator/fusion.py`\n\n"
                    "```python\ndef broken(:\n```\n\n```sh\nesiaf run --input a.wav --no-such-option\n"
                    "esiaf frobnicate\nesiaf eval robocup --runs 2 -- --fast\n```\n")
    assert [b.split(":")[0] for b in broken_links(page)] == ["missing.md", "there.md#nothing"]
    assert missing_files(page) == ["esiaf_services/orchestrator/fusion.py"]
    assert len([code for _, code in python_blocks(page)]) == 1
    with pytest.raises(SyntaxError):
        compile(next(python_blocks(page))[1], "page", "exec")
    problems = [command_problem(command) for command in command_lines(page)]
    assert problems[0] and "--no-such-option" in problems[0]
    assert problems[1] and "frobnicate" in problems[1]
    assert problems[2] is None
    assert docgen.main(["--check", "--output", str(page)]) == 1
