"""The README and docs/ stay true to the code: the option reference is the config schema's, every
--flag they name exists in the config schema or in the named command's own parser, every
repository path and relative link they name exists, and the code cites only pages of the
repository. Static reading only (no process, no network, no torch): fast and deterministic."""

from __future__ import annotations

import ast
import os
import re
from collections import defaultdict
from functools import cache
from pathlib import Path

import pytest

from common.config_values import config_fields
from deploy.tools import option_reference

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
README_MAX_LINES = 250

# The command a doc line starts with -> the source file that builds its parser.
COMMANDS = {
    "replay": "replay/main.py", "replay.main": "replay/main.py",
    "learner": "learner/main.py", "learner.main": "learner/main.py",
    "actor": "actor/main.py", "actor.main": "actor/main.py",
    "evaluate": "actor/evaluation/command.py",
    "d3rqn-log": "replay/recorder/cli.py",  # the next word is its subcommand
    "d3rqn-certs": "common/certs.py",
    "deploy/run.sh": "deploy/launcher/stack.py",
    "deploy.reference_loop": "deploy/reference_loop.py",
}
EXTERNAL = {"pip", "tensorboard", "python3.11", "source", "openssl", "deploy/test.sh",  # flags not ours
            "sbatch", "squeue", "scontrol", "scancel", "rsync"}
# A command whose flags it does not take itself go on to another's parser: that one's flags are its too.
PASSED_ON = {"deploy/slurm/submit.py": "deploy/grid/experiments.py"}
CONFIG_ENTRY_POINTS = {"add_config_arguments", "parse_service_args"}  # a parser these get has every config flag
ON_PURPOSE_WRONG = {"--run.nam"}  # docs/configuration.md shows how a mistyped flag is refused

FLAG = re.compile(r"(?<![\w-])--[a-z](?:[a-z0-9_.-]*[a-z0-9_])?(\.\*)?")
SHELL_FLAG = re.compile(r'"(--[a-z][a-z0-9-]*)"')  # a flag a script of ours tests for: [ "$1" = "--wheels" ]
CODE_BLOCK = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
CODE_SPAN = re.compile(r"`([^`]+)`")
LINK = re.compile(r"\]\(([^)\s]+)\)")
HEADING = re.compile(r"^(#{1,6}) (.+?)\s*$", re.M)
METHOD_CITATION = re.compile(r'docs/method\.md(?:,\s*|\s*\()"([^"]+)"')
SPEC = "REFERENCE" + ".md"  # the shared spec outside the repository (spelt so that this file does not name it)


def top_level_folders() -> set[str]:
    skip = {"runs", "build", "__pycache__"}
    return {path.name for path in ROOT.iterdir() if path.is_dir() and path.name not in skip
            and (not path.name.startswith(".") or path.name == ".ci") and not path.name.endswith(".egg-info")}


@cache
def config_flags() -> frozenset[str]:
    return frozenset({f"--{key}" for key in config_fields()} | {"--preset", "--config", "--dump-config"})


@cache
def parser_flags(relative: str) -> dict[str | None, frozenset[str]]:
    """The flags of the argparse parsers a source file builds, by subcommand (None: the main parser),
    read from its syntax tree: add_argument("--x", ...) calls, with --no-x for a BooleanOptionalAction,
    and every config flag for a parser handed to add_config_arguments or parse_service_args."""
    tree = ast.parse((ROOT / relative).read_text())
    subcommand = {}  # variable -> subcommand name, from `var = subparsers.add_parser("name", ...)`
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call)
                and isinstance(node.value.func, ast.Attribute) and node.value.func.attr == "add_parser"):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    subcommand[target.id] = node.value.args[0].value
    flags: dict[str | None, set[str]] = defaultdict(lambda: {"--help"})
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Attribute) and func.attr == "add_argument":
            owner = subcommand.get(func.value.id) if isinstance(func.value, ast.Name) else None
            boolean = any(kw.arg == "action" and "BooleanOptionalAction" in ast.unparse(kw.value)
                          for kw in node.keywords)
            for arg in node.args:
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and arg.value.startswith("--"):
                    flags[owner].add(arg.value)
                    if boolean:
                        flags[owner].add("--no-" + arg.value[2:])
        elif isinstance(func, ast.Name) and func.id in CONFIG_ENTRY_POINTS and node.args:
            target = node.args[0]
            flags[subcommand.get(target.id) if isinstance(target, ast.Name) else None].update(config_flags())
    return {key: frozenset(value) for key, value in flags.items()}


@cache
def every_flag() -> frozenset[str]:
    sources = set(COMMANDS.values()) | {str(path.relative_to(ROOT)) for path in (ROOT / "deploy").rglob("*.py")}
    return frozenset().union(config_flags(), *(flags for source in sources
                                               for flags in parser_flags(source).values()))


def command_flags(line: str) -> tuple[str, frozenset[str] | None]:
    """The command a shell line runs and the flags its parser takes: (name, None) for a command that is
    not ours, ("", every flag) for a line that runs no known command (output, prose)."""
    words = line.replace("\\\n", " ").split()
    words = words[1:] if words[:1] == ["$"] else words
    if not words:
        return "", every_flag()
    word = words[0].removeprefix(".venv/bin/")
    if word in ("python", "python3") and len(words) > 1:
        word = words[2] if words[1] == "-m" and len(words) > 2 else words[1]
    if word in EXTERNAL:
        return word, None
    if word.endswith(".sh") and word not in COMMANDS and (ROOT / word).is_file():
        return word, frozenset(SHELL_FLAG.findall((ROOT / word).read_text()))
    if word.endswith(".py") and "/" not in word and (ROOT / "deploy" / "bench" / word).exists():
        word = f"deploy/bench/{word}"
    source = COMMANDS.get(word) or (word if word.endswith(".py") and (ROOT / word).is_file() else None)
    if source is None:
        return "", every_flag()
    by_subcommand = parser_flags(source)
    flags = set(by_subcommand.get(None, frozenset({"--help"})))
    if source in PASSED_ON:
        flags |= parser_flags(PASSED_ON[source])[None]
    subcommand = next((later for later in words[1:] if later in by_subcommand), None)
    if subcommand is not None:  # `d3rqn-log info ...`, `deploy/studies/study.py run ...`: that subcommand's flags too
        flags |= by_subcommand[subcommand]
    return word, frozenset(flags)


def unknown_flags(text: str, known: frozenset[str]) -> list[str]:
    wrong = []
    for match in FLAG.finditer(text):
        flag, wildcard = match.group(0).removesuffix(".*"), match.group(1)
        if flag in ON_PURPOSE_WRONG:
            continue
        if wildcard and any(name.startswith(flag + ".") for name in known):
            continue
        if flag not in known:
            wrong.append(flag)
    return wrong


def shell_lines(block: str) -> list[str]:
    joined = re.sub(r"\\\n\s*", " ", block)
    return [re.sub(r"\s#.*$", "", line) for line in joined.splitlines() if not line.lstrip().startswith("#")]


def page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", PAGES, ids=page_id)
def test_every_flag_the_page_names_exists(page):
    text = page.read_text()
    wrong = []
    for block in CODE_BLOCK.findall(text):
        for line in shell_lines(block):
            name, known = command_flags(line)
            if known is not None:
                wrong += [f"{flag} (in `{line.strip()[:60]}`, {name or 'no command of ours'})"
                          for flag in unknown_flags(line, known)]
    prose = CODE_BLOCK.sub("", text)
    for span in CODE_SPAN.findall(prose):
        name, known = command_flags(span)
        if known is not None:
            wrong += [f"{flag} (in `{span[:60]}`)" for flag in unknown_flags(span, known)]
    wrong += [f"{flag} (in the text)" for flag in unknown_flags(CODE_SPAN.sub("", prose), every_flag())]
    assert not wrong, f"{page_id(page)} names flags that no parser takes: {wrong}"


def slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    text = re.sub(r"[`*]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading).strip().lower()
    return "".join(char for char in text if char.isalnum() or char in " -_").replace(" ", "-")


@cache
def anchors(page: Path) -> frozenset[str]:
    seen: dict[str, int] = defaultdict(int)
    found = set()
    for _, heading in HEADING.findall(CODE_BLOCK.sub("", page.read_text())):
        base = slug(heading)
        found.add(base if seen[base] == 0 else f"{base}-{seen[base]}")
        seen[base] += 1
    return frozenset(found)


def repository_paths(text: str) -> set[str]:
    """Tokens that name a file or folder of the repository: they start with a top-level folder and end
    with a file name that has an extension, or with a slash. Zenoh keys (replay/rate) have neither;
    paths inside a run folder are written after runs/<run>/ or <run>/, which this leaves out."""
    folders = "|".join(re.escape(name) for name in sorted(top_level_folders()))
    pattern = re.compile(rf"(?<![\w/.<>&;-])((?:{folders})/[\w./-]*)")
    paths = set()
    for match in pattern.finditer(text):
        if text[match.end():match.end() + 1] == "<":
            continue  # a template such as replay/stats/<value>
        token = match.group(1).rstrip(".,;:")
        if token.endswith("/") or "." in token.rsplit("/", 1)[-1]:
            paths.add(token)
    return paths


@pytest.mark.parametrize("page", PAGES, ids=page_id)
def test_every_path_and_link_the_page_names_exists(page):
    text = page.read_text()
    named = repository_paths(LINK.sub("]()", text))  # link targets are relative to the page: checked below
    missing = [path for path in sorted(named) if not (ROOT / path).exists()]
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.exists() or ROOT not in (resolved, *resolved.parents):
            missing.append(f"link {target}")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            missing.append(f"link {target} (no such heading)")
    assert not missing, f"{page_id(page)} names what the repository does not hold: {missing}"


def test_the_option_reference_is_the_config_schemas():
    page = option_reference.PAGE.read_text()
    assert option_reference.BEGIN in page and option_reference.END in page
    assert option_reference.current_reference(page) == option_reference.reference(), (
        "docs/configuration.md's option reference is stale: run `.venv/bin/python deploy/tools/option_reference.py "
        "--write`")


def test_the_option_reference_lists_every_option():
    reference = option_reference.reference()
    assert all(f"`--{key}`" in reference for key in config_fields())


def test_the_readme_is_a_front_door():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; the details belong in docs/"
    index = (ROOT / "README.md").read_text().split("## Documentation", 1)[1]
    listed = {target for target in LINK.findall(index)}
    pages = {page_id(page) for page in PAGES if page.parent == ROOT / "docs"}
    assert pages <= listed, f"README's documentation index lacks {sorted(pages - listed)}"


def source_files() -> list[Path]:
    skip = {".git", ".venv", "runs", "build", "__pycache__", ".pytest_cache", ".hypothesis"}
    suffixes = {".py", ".md", ".toml", ".sh", ".txt", ""}
    files = []
    for folder, folders, names in os.walk(ROOT):
        folders[:] = [name for name in folders if name not in skip and not name.endswith(".egg-info")]
        files += [Path(folder) / name for name in names if Path(name).suffix in suffixes]
    return files


def test_nothing_cites_the_spec_outside_the_repository():
    citing = [str(path.relative_to(ROOT)) for path in source_files()
              if SPEC in path.read_text(errors="replace")]
    assert not citing, f"{citing} cite {SPEC}, which is not in the repository; cite docs/method.md"


def test_code_cites_sections_of_the_method_page_that_exist():
    headings = {" ".join(heading.split()) for _, heading in HEADING.findall((ROOT / "docs" / "method.md").read_text())}
    cited = {(str(path.relative_to(ROOT)), " ".join(section.split()))
             for path in source_files() if path.suffix == ".py"
             for section in METHOD_CITATION.findall(path.read_text())}
    assert cited, "the code cites docs/method.md"
    assert not [c for c in cited if c[1] not in headings], f"no such section in docs/method.md: {cited}"
