"""The documents hold up: every relative link of README.md and docs/*.md reaches a file (and a
heading, for `#anchor` links, named as GitHub names them), every `make X` quoted names a
Makefile target, every `renderfarm SUB ...` and `renderfarm-worker SUB ...` quoted names a
subcommand and flags that exist, and every `RENDERFARM_*` variable named exists in the code.

Fast: no farm. The CLI's subcommands and flags come from `python -m renderfarm SUB --help`,
the worker's from `renderfarm-worker --help` (the binary tests/conftest.py finds). Each problem
is reported as `FILE:LINE: what`.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# Where a RENDERFARM_* variable may be read: the server package, the worker, the deployments
# and scripts, the Blender add-on, the benchmarks (not the tests, not the documents).
CODE_DIRS = ["server/renderfarm", "worker", "deploy", "scripts", "integrations", "bench"]
CODE_SUFFIXES = {
    ".py",
    ".c",
    ".cpp",
    ".h",
    ".hpp",
    ".txt",
    ".cmake",
    ".sh",
    ".yaml",
    ".yml",
    ".env",
    ".example",
    ".toml",
    ".proto",
    ".json",
    "",
}


# ------------------------------------------------------------------------------ markdown
@dataclass
class Block:
    """A code block: its first line's number, its lines, its fence's info string."""

    line: int
    lines: list[str]
    info: str = ""


@dataclass
class Document:
    path: Path
    text: str
    prose: str = ""  # the text with code blocks blanked (line numbers kept)
    blocks: list[Block] = field(default_factory=list)
    headings: list[tuple[int, str]] = field(default_factory=list)

    @property
    def name(self) -> str:
        try:
            return str(self.path.relative_to(ROOT))
        except ValueError:
            return str(self.path)


def parse(path: Path, text: str | None = None) -> Document:
    """Split a Markdown file into code blocks (fenced, or indented after a blank line) and the
    rest, and list its ATX headings (outside code)."""
    doc = Document(path, path.read_text() if text is None else text)
    lines = doc.text.split("\n")
    prose: list[str] = []
    fence: str | None = None
    block: Block | None = None
    previous_blank = True
    for number, line in enumerate(lines, 1):
        if fence is not None:  # inside a fenced block
            prose.append("")
            if line.strip().startswith(fence):
                fence, block = None, None
            else:
                assert block is not None
                block.lines.append(line)
            continue
        opening = re.match(r"^ {0,3}(`{3,}|~{3,})\s*(\S*)", line)
        if opening:
            fence = opening.group(1)
            block = Block(number + 1, [], opening.group(2))
            doc.blocks.append(block)
            prose.append("")
            continue
        indented = line.startswith(("    ", "\t"))
        if indented and (block is not None or previous_blank):
            if block is None:
                block = Block(number, [])
                doc.blocks.append(block)
            block.lines.append(line[4:] if line.startswith("    ") else line[1:])
            prose.append("")
            previous_blank = False
            continue
        if block is not None and not line.strip():
            # A blank line inside an indented block, unless the block ends here.
            following = next((x for x in lines[number:] if x.strip()), "")
            if following.startswith(("    ", "\t")):
                block.lines.append("")
                prose.append("")
                continue
        block = None
        prose.append(line)
        previous_blank = not line.strip()
        heading = re.match(r"^ {0,3}#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            doc.headings.append((number, heading.group(1)))
    doc.prose = "\n".join(prose)
    return doc


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: the rendered text, lower case, without punctuation but
    hyphens and underscores, spaces made hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link shows its text
    text = text.replace("`", "").replace("*", "")
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def anchors(doc: Document) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for _, heading in doc.headings:
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def code_spans(doc: Document) -> Iterator[tuple[int, str]]:
    """Inline code of the prose (a span may wrap onto the next line), with its line number."""
    for m in re.finditer(r"(`+)(.+?)\1", doc.prose, flags=re.S):
        yield doc.prose.count("\n", 0, m.start()) + 1, " ".join(m.group(2).split())


def without_code_spans(prose: str) -> str:
    return re.sub(r"(`+)(.+?)\1", lambda m: re.sub(r"[^\n]", " ", m.group(0)), prose, flags=re.S)


def block_lines(doc: Document) -> Iterator[tuple[int, str]]:
    """Each logical line of the shell code blocks (backslash continuations joined), without its
    comment. ASCII diagrams (a line starting `+---`) and blocks of other languages are
    skipped."""
    for block in doc.blocks:
        if block.info and block.info not in {"sh", "bash", "shell", "console"}:
            continue
        if any(re.match(r"^\s*\+-{3,}", line) for line in block.lines):
            continue
        pending, start = "", block.line
        for offset, line in enumerate(block.lines):
            if not pending:
                start = block.line + offset
            if line.rstrip().endswith("\\"):
                pending += line.rstrip()[:-1] + " "
                continue
            yield start, re.sub(r"(^|\s)#.*$", "", pending + line).strip()
            pending = ""


# ------------------------------------------------------------------------------ commands
@dataclass
class Tool:
    """A command line: its subcommands with their flags, nested subcommands, top-level flags."""

    name: str
    top_flags: set[str]
    subcommands: dict[str, set[str]]
    nested: dict[str, dict[str, set[str]]] = field(default_factory=dict)


COMMAND = re.compile(
    r"^(?:\$\s+)?(?:sudo\s+)?(?:[A-Z_][A-Z0-9_]*=\S*\s+)*"
    r"(?:\S*bin/)?(?P<tool>renderfarm-worker|renderfarm|make)(?:\s+(?P<rest>.*))?$"
)
FLAG = re.compile(r"(?<![\w-])(--?[A-Za-z][\w-]*)")


def segments(command_line: str) -> Iterator[str]:
    """The commands of a shell line: split at `&&`, `||` and `;`, cut at a pipe into another
    command (`| head`; `drain|disable` and `--help | --version` are one command's syntax)."""
    for part in re.split(r"&&|\|\||;", command_line):
        yield re.split(r"\s\|\s+(?=[a-z])", part)[0].strip()


def check_command(where: str, text: str, tools: dict[str, Tool], targets: set[str]) -> list[str]:
    problems = []
    for segment in segments(text):
        m = COMMAND.match(segment)
        if not m:
            continue
        tool, rest = m.group("tool"), (m.group("rest") or "").strip()
        if tool == "make":
            target = rest.split()[0] if rest else ""
            if target and not re.match(r"^[\w-]+$", target):
                continue  # `make` as a word of prose, not a command
            if target and target not in targets:
                problems.append(f"{where}: `make {target}`: no such Makefile target")
            continue
        spec = tools[tool]
        words = rest.split()
        if not words:
            continue
        sub = words[0]
        if sub.startswith("-"):
            allowed = spec.top_flags
            label = tool
        elif sub in spec.subcommands:
            allowed = spec.subcommands[sub]
            label = f"{tool} {sub}"
            nested = spec.nested.get(sub)
            if nested and len(words) > 1 and not words[1].startswith("-"):
                if words[1] in nested:
                    allowed = nested[words[1]]
                    label = f"{tool} {sub} {words[1]}"
                elif re.match(r"^[a-z]+$", words[1]):
                    problems.append(f"{where}: `{label} {words[1]}`: no such subcommand")
                    continue
        else:
            problems.append(f"{where}: `{tool} {sub}`: no such subcommand")
            continue
        for flag in FLAG.findall(rest):
            if flag not in allowed and flag not in {"-h", "--help"}:
                problems.append(f"{where}: `{label}` has no flag {flag}")
    return problems


def check_commands(doc: Document, tools: dict[str, Tool], targets: set[str]) -> list[str]:
    problems = []
    for line, text in block_lines(doc):
        problems += check_command(f"{doc.name}:{line}", text, tools, targets)
    for line, span in code_spans(doc):
        problems += check_command(f"{doc.name}:{line}", span, tools, targets)
    return problems


# ------------------------------------------------------------------------------ links
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def check_links(doc: Document, parsed: dict[Path, Document]) -> list[str]:
    problems = []
    prose = without_code_spans(doc.prose)
    for m in LINK.finditer(prose):
        target = m.group(1)
        where = f"{doc.name}:{prose.count(chr(10), 0, m.start()) + 1}"
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        path = (doc.path.parent / path_part).resolve() if path_part else doc.path
        if not path.exists():
            problems.append(f"{where}: link to {target}: {path_part} does not exist")
            continue
        if not anchor:
            continue
        if path.suffix != ".md" or path.is_dir():
            problems.append(f"{where}: link to {target}: an anchor in a file not Markdown")
            continue
        if path not in parsed:
            parsed[path] = parse(path)
        if anchor not in anchors(parsed[path]):
            problems.append(f"{where}: link to {target}: {path.name} has no heading #{anchor}")
    return problems


# ------------------------------------------------------------------------------ variables
def check_variables(doc: Document, known: set[str]) -> list[str]:
    problems = []
    for number, line in enumerate(doc.text.split("\n"), 1):
        for name in re.findall(r"\bRENDERFARM_[A-Z0-9_]*[A-Z0-9]\b", line):
            if name not in known:
                problems.append(f"{doc.name}:{number}: {name} is read nowhere in {CODE_DIRS}")
    return problems


# ------------------------------------------------------------------------------ fixtures
# One interpreter runs `python -m renderfarm ARGS --help` for every ARGS (runpy, as `-m` does),
# each help after a separator line: one process instead of one per subcommand.
HELP_RUNNER = """
import contextlib, io, json, runpy, sys
for args in json.loads(sys.argv[1]):
    sys.argv = ["renderfarm", *args, "--help"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        runpy.run_module("renderfarm", run_name="__main__", alter_sys=True)
    print("\\f" + json.dumps(args) + "\\n" + out.getvalue(), end="")
"""


def _helps(commands: list[list[str]]) -> dict[tuple[str, ...], str]:
    env = {**os.environ, "COLUMNS": "200", "PYTHONPATH": str(ROOT / "server")}
    if os.environ.get("PYTHONPATH"):
        env["PYTHONPATH"] += os.pathsep + os.environ["PYTHONPATH"]
    out = subprocess.run(
        [sys.executable, "-c", HELP_RUNNER, json.dumps(commands)],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=120,
    )
    assert out.returncode == 0, f"python -m renderfarm --help: exit {out.returncode}: {out.stderr}"
    helps = {}
    for chunk in out.stdout.split("\f")[1:]:
        args, _, text = chunk.partition("\n")
        helps[tuple(json.loads(args))] = text
    assert len(helps) == len(commands) and all(helps.values()), (commands, out.stderr)
    return helps


def _choices(help_text: str) -> list[str]:
    """The subcommands argparse lists as `{a,b,c}` in a usage line followed by `...`."""
    m = re.search(r"\{([\w,-]+)\}\s+\.\.\.", help_text)
    return m.group(1).split(",") if m else []


def _flags(help_text: str) -> set[str]:
    return set(FLAG.findall(help_text))


@pytest.fixture(scope="module")
def cli() -> Tool:
    top = _helps([[]])[()]
    subs = _choices(top)
    assert {"server", "render", "submit", "token"} <= set(subs), top
    helps = {args[0]: text for args, text in _helps([[sub] for sub in subs]).items()}
    children = [[sub, child] for sub in subs for child in _choices(helps[sub])]
    nested: dict[str, dict[str, set[str]]] = {}
    for (sub, child), text in _helps(children).items():
        nested.setdefault(sub, {})[child] = _flags(text)
    top_flags = _flags(top.split("positional arguments")[0]) | {"--log-level"}
    return Tool("renderfarm", top_flags, {s: _flags(h) for s, h in helps.items()}, nested)


@pytest.fixture(scope="module")
def worker(worker_binary) -> Tool:
    out = subprocess.run([worker_binary, "--help"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    subcommands: dict[str, set[str]] = {}
    top: set[str] = set()
    current: set[str] | None = None
    for line in out.stdout.splitlines():
        m = re.match(r"^\s*renderfarm-worker\s+(\S+)(.*)$", line)
        if m and not m.group(1).startswith("-"):
            current = subcommands.setdefault(m.group(1), set())
            current |= _flags(m.group(2))
        elif m:
            current = top
            top |= _flags(m.group(1) + m.group(2))
        elif current is not None:
            current |= _flags(line)
    assert {"connect", "inspect", "render"} <= set(subcommands), out.stdout
    assert "--server" in subcommands["connect"], out.stdout
    return Tool("renderfarm-worker", top, subcommands)


@pytest.fixture(scope="module")
def targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    found = set(re.findall(r"^([\w.-]+)\s*:(?!=)", text, flags=re.M))
    assert {"demo", "test", "build"} <= found
    return found


@pytest.fixture(scope="module")
def variables(cli) -> set[str]:
    known = {f"RENDERFARM_{f[2:].replace('-', '_').upper()}" for f in cli.subcommands["server"]}
    for directory in CODE_DIRS:
        for path in (ROOT / directory).rglob("*"):
            if path.is_file() and (path.suffix in CODE_SUFFIXES or path.name.endswith("file")):
                try:
                    known |= set(re.findall(r"RENDERFARM_[A-Z0-9_]*[A-Z0-9]", path.read_text()))
                except (UnicodeDecodeError, OSError):
                    continue
    return known


@pytest.fixture(scope="module")
def documents() -> dict[Path, Document]:
    assert (ROOT / "docs" / "README.md") in DOCUMENTS
    return {path: parse(path) for path in DOCUMENTS}


# ------------------------------------------------------------------------------ the checks
def _report(problems: list[str]) -> str:
    return f"{len(problems)} problem(s):\n" + "\n".join(problems)


def test_every_relative_link_reaches_a_file_and_heading(documents):
    parsed = dict(documents)
    problems = [p for doc in documents.values() for p in check_links(doc, parsed)]
    assert not problems, _report(problems)
    # The documents do link to each other: the check saw links (and anchors) to check.
    links = [m.group(1) for doc in documents.values() for m in LINK.finditer(doc.prose)]
    assert sum("#" in link for link in links) >= 10 and len(links) >= 40, links


def test_every_quoted_command_exists(documents, cli, worker, targets):
    tools = {"renderfarm": cli, "renderfarm-worker": worker}
    problems = [p for doc in documents.values() for p in check_commands(doc, tools, targets)]
    assert not problems, _report(problems)
    # The README quotes its two set-up commands in a code block, and the checks see them.
    readme = documents[ROOT / "README.md"]
    quoted = [text for _, text in block_lines(readme)]
    assert any(t.startswith("make demo") for t in quoted), quoted
    assert any(t.startswith("make test") for t in quoted), quoted


def test_every_renderfarm_variable_named_exists(documents, variables):
    problems = [p for doc in documents.values() for p in check_variables(doc, variables)]
    assert not problems, _report(problems)


def test_readme_is_a_few_screens_with_two_setup_commands(documents):
    readme = documents[ROOT / "README.md"]
    assert len(readme.text.encode()) < 8192, f"README.md is {len(readme.text.encode())} bytes"
    setup = next(b for b in readme.blocks if any("make demo" in x for x in b.lines))
    commands = [x.split("#")[0].strip() for x in setup.lines if x.split("#")[0].strip()]
    assert commands == ["make demo", "make test"], commands
    linked = set(re.findall(r"\]\(docs/([\w-]+\.md)", readme.prose))
    pages = {p.name for p in (ROOT / "docs").glob("*.md")} - {"README.md"}
    assert pages <= linked, f"README.md does not list {sorted(pages - linked)}"


# ------------------------------------------------------------------------------ the checks fail
FAKE_CLI = Tool(
    "renderfarm",
    {"--log-level"},
    {"get": {"-o", "--layer"}, "token": set()},
    {"token": {"create": {"--admin"}}},
)
FAKE_WORKER = Tool("renderfarm-worker", {"--help", "--version"}, {"connect": {"--server"}})
FAKE_TOOLS = {"renderfarm": FAKE_CLI, "renderfarm-worker": FAKE_WORKER}


def _fake(tmp_path: Path, text: str) -> Document:
    path = tmp_path / "page.md"
    path.write_text(text)
    (tmp_path / "other.md").write_text("# Other\n\n## A job's progress\n")
    return parse(path)


def test_the_checks_name_file_and_line_of_each_fault(tmp_path):
    doc = _fake(
        tmp_path,
        "# Page\n\n"
        "Fine: [other](other.md#a-jobs-progress), [here](#page), [web](https://x.invalid/#y).\n"
        "Broken: [gone](missing.md), [anchor](other.md#no-such-heading).\n"
        "\n"
        "    make demo         # a target\n"
        "    make nosuchtarget\n"
        "    renderfarm get ID -o out.exr --layer rgb\n"
        "    renderfarm get ID --bogus\n"
        "    RENDERFARM_URL=x .venv/bin/renderfarm frobnicate\n"
        "    renderfarm token create NAME --admin && renderfarm token destroy 3\n"
        "    renderfarm-worker connect --server h:1 \\\n"
        "        --threads 4\n"
        "\n"
        "Inline `renderfarm-worker --help | --version` and `renderfarm-worker\n"
        "render X --spp 4`. `RENDERFARM_NOT_A_SETTING` and `RENDERFARM_URL`.\n",
    )
    parsed = {doc.path: doc}
    links = check_links(doc, parsed)
    at = f"{tmp_path / 'page.md'}:4: "
    assert len(links) == 2 and all(p.startswith(at) for p in links), links
    assert "missing.md does not exist" in links[0], links
    assert "has no heading #no-such-heading" in links[1], links

    commands = check_commands(doc, FAKE_TOOLS, {"demo", "test"})
    lines = [p.split(": ", 1) for p in commands]
    assert [(w.rsplit(":", 1)[1], what) for w, what in lines] == [
        ("7", "`make nosuchtarget`: no such Makefile target"),
        ("9", "`renderfarm get` has no flag --bogus"),
        ("10", "`renderfarm frobnicate`: no such subcommand"),
        ("11", "`renderfarm token destroy`: no such subcommand"),
        ("12", "`renderfarm-worker connect` has no flag --threads"),
        ("15", "`renderfarm-worker render`: no such subcommand"),
    ], commands

    variables = check_variables(doc, {"RENDERFARM_URL"})
    assert len(variables) == 1 and variables[0].endswith(
        ":16: RENDERFARM_NOT_A_SETTING is read nowhere in " + str(CODE_DIRS)
    ), variables


def test_slugs_are_githubs():
    assert slug("REST API (`/api/v1`, OpenAPI at `/docs` and `/openapi.json`)") == (
        "rest-api-apiv1-openapi-at-docs-and-openapijson"
    )
    assert slug("A job's progress") == "a-jobs-progress"
    assert slug("Checks, and the topology without Docker") == (
        "checks-and-the-topology-without-docker"
    )
    assert slug("Set-up (Debian 12)") == "set-up-debian-12"
    assert slug("`max_spp` and **bold**") == "max_spp-and-bold"
    doc = parse(Path("x.md"), "# Same\n\n## Same\n\n    # not a heading\n")
    assert anchors(doc) == {"same", "same-1"}
