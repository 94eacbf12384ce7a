"""Find the references the docs, notebooks and comments make, and check that each still holds.

A reference is a repository path, a markdown link, a section citation (`docs/NAME.md,
"Heading"`), an `xvoe ...` command line, a `python benchmarks/X.py ...` command, a dotted
`xvoe.NAME` or a `--flag` named in prose. Docs are read by people who cannot ask what a renamed
file or flag used to be, so tests/test_references.py fails on any dead one, at file:line.
Nothing here runs a command: `xvoe` lines are parsed by the real argument parser, benchmark
flags are read from the scripts' `add_argument` calls.
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import difflib
import io
import re
import shlex
import tokenize
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import nbformat

ROOT = Path(__file__).resolve().parent.parent
# The top-level directories a bare path in prose is read against (from the repository's root).
TOP = ("xvoe", "docs", "benchmarks", "inference", "tests", "notebooks")
# Paths the docs name that running something writes, not files of the repository.
GENERATED = ("notebooks/notebook-data",)


@dataclass(frozen=True)
class Text:
    """A stretch of one file: prose (markdown, a comment, a docstring) or a code block.

    `text` keeps the file's line breaks, so an offset into it maps back to a line of `where`.
    `code` is "" for prose, else the code block's language ("shell" for an unlabelled block).
    """

    path: Path          # the file, for relative links
    where: str          # how a failure names the file: "README.md", "notebooks/x.ipynb cell 3"
    line: int           # the line of `where` that text[0] is on (1-based)
    text: str
    code: str = ""

    def at(self, offset: int) -> str:
        return f"{self.where}:{self.line + self.text.count(chr(10), 0, offset)}"


@dataclass(frozen=True)
class Dead:
    """One dead reference: where it is and what is wrong with it."""

    where: str
    reference: str
    why: str

    def __str__(self) -> str:
        return f"{self.where}: {' '.join(self.reference.split())!r}: {self.why}"


# ---------------------------------------------------------------------------------------------
# The texts: markdown (prose and fenced blocks), notebook cells, Python comments and docstrings

FENCE = re.compile(r"^ {0,3}(```+|~~~+)\s*([\w+-]*)")      # ``` or ~~~, and the block's language


def markdown_texts(source: str, path: Path, where: str, line: int = 1) -> list[Text]:
    """The prose of a markdown text (its code blocks blanked, lines kept) and each code block."""
    prose, texts, block, fence, language, start = [], [], [], "", "", 0
    for number, row in enumerate(source.split("\n")):
        opened = FENCE.match(row)
        if not fence and opened:
            fence, language, block, start = opened.group(1), opened.group(2) or "shell", [], number + 1
            prose.append("")
        elif fence and row.strip().startswith(fence):
            texts.append(Text(path, where, line + start, "\n".join(block), language))
            fence = ""
            prose.append("")
        elif fence:
            block.append(row)
            prose.append("")
        else:
            prose.append(row)
    return [Text(path, where, line, "\n".join(prose)), *texts]


def notebook_texts(path: Path) -> list[Text]:
    """Every cell of a notebook: markdown cells as markdown, code cells as Python code."""
    notebook = nbformat.read(path, as_version=4)
    texts = []
    for number, cell in enumerate(notebook.cells):
        where = f"{relative(path)} cell {number}"
        if cell.cell_type == "markdown":
            texts += markdown_texts(cell.source, path, where)
        elif cell.cell_type == "code":
            texts.append(Text(path, where, 1, cell.source, "python"))
    return texts


DEFINITIONS = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)      # what may have a docstring


def python_texts(path: Path) -> list[Text]:
    """A module's comments (a run of consecutive comment lines is one text) and docstrings."""
    source = path.read_text()
    texts, run, first, last = [], [], 0, -1
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type != tokenize.COMMENT:
            continue
        row = token.start[0]
        if row != last + 1 and run:
            texts.append(Text(path, relative(path), first, "\n".join(run)))
            run = []
        if not run:
            first = row
        run.append(token.string.lstrip("#").strip())
        last = row
    if run:
        texts.append(Text(path, relative(path), first, "\n".join(run)))
    statements = [ast.parse(source)]
    while statements:                   # statements only: a docstring is never inside an expression
        node = statements.pop()
        body = [child for field in ("body", "orelse", "finalbody", "handlers") for child in getattr(node, field, [])]
        statements += [child for child in body if isinstance(child, ast.stmt | ast.excepthandler)]
        first = node.body[0] if isinstance(node, DEFINITIONS) and node.body else None
        if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
            texts.append(Text(path, relative(path), first.lineno, first.value.value))
    return texts


def relative(path: Path) -> str:
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(path)


@cache
def repository_texts(root: Path = ROOT) -> tuple[Text, ...]:
    """Everything the references test reads. docs/log/ is history, quoted as it was: not read."""
    texts: list[Text] = []
    for path in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        texts += markdown_texts(path.read_text(), path, relative(path))
    for path in sorted((root / "notebooks").glob("*.ipynb")):
        texts += notebook_texts(path)
    for pattern in ("xvoe/**/*.py", "inference/**/*.py", "benchmarks/*.py"):
        for path in sorted(root.glob(pattern)):
            texts += python_texts(path)
    return tuple(texts)


# ---------------------------------------------------------------------------------------------
# Commands: where they are and how they split into arguments

SHELL = ("shell", "sh", "bash", "console", "text")
INLINE_CODE = re.compile(r"(?<!`)`([^`]+)`(?!`)")
COMMENT = re.compile(r"(?:^|\s)#.*", re.S)
SEPARATOR = re.compile(r";|&&|\|\||\s\|\s")
REDIRECTION = re.compile(r"\s(?:[12]?>>?|<).*", re.S)


def command_lines(text: Text) -> Iterator[tuple[int, str, bool]]:
    """(offset, line, inline): each line of a shell code block (a line continued by a backslash is
    one), and each `inline code` span of prose (a mention, which may leave arguments out)."""
    if text.code in SHELL:
        offset = 0
        for row in re.split(r"(?<!\\)\n", text.text):
            yield offset, row.replace("\\\n", " "), False
            offset += len(row) + 1
    elif not text.code:
        for span in INLINE_CODE.finditer(text.text):
            yield span.start(1), " ".join(span.group(1).split()), True


def commands(text: Text) -> Iterator[tuple[int, str, bool]]:
    """(offset, command, inline) of every shell command: a line is cut at a comment and split at
    `;`, `&&`, `||` and ` | `; a redirection is dropped."""
    for offset, line, inline in command_lines(text):
        for part in SEPARATOR.split(COMMENT.sub("", line)):
            yield offset, REDIRECTION.sub("", part).strip(" ()"), inline      # (cd dir && xvoe ...)


def arguments_after(command: str, program: Callable[[list[str], int], bool]) -> list[str] | None:
    """The arguments of `command` after the token `program` accepts, or None if no token does."""
    try:
        tokens = shlex.split(command)
    except ValueError:
        return None
    for index, _ in enumerate(tokens):
        if program(tokens, index):
            return tokens[index + 1:]
    return None


def is_xvoe(tokens: list[str], index: int) -> bool:
    """`xvoe`, `.venv/bin/xvoe` (after any VAR=value) or `python -m xvoe` / `torchrun ... -m xvoe`."""
    token = tokens[index]
    if token == "xvoe" and index > 0 and tokens[index - 1] == "-m":
        return True
    leading = all("=" in before and not before.startswith("-") for before in tokens[:index])
    return leading and (token == "xvoe" or token.endswith("/bin/xvoe"))


def is_benchmark(tokens: list[str], index: int) -> bool:
    """benchmarks/X.py run by a python: `python benchmarks/X.py`, `.venv/bin/python benchmarks/...`."""
    return (index > 0 and re.fullmatch(r"benchmarks/\w+\.py", tokens[index]) is not None
            and re.search(r"(^|/)python3?$", tokens[index - 1]) is not None)


# Placeholders a command may hold for a value: RUN, FILE, M, N/4, I/N, R0,R1,R2.
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9_]*(?:[/,][A-Z0-9_]+)*")


def parse_error(parser: argparse.ArgumentParser, arguments: list[str], inline: bool) -> str | None:
    """Why `parser` refuses `arguments`, or None. Never runs anything.

    A placeholder the parser refuses as a value (`--seed S`) is no error; `[--flag value]` is an
    optional part; `xpl|plato` is each of xpl and plato. A mention in prose (`inline`) may leave
    out required arguments (`xvoe score`) and a flag's value (`xvoe score --shard`).
    """
    arguments = [argument.strip("[]") for argument in arguments if argument.strip("[]")]
    choices = max((argument.count("|") + 1 for argument in arguments), default=1)
    for choice in range(choices):
        chosen = [argument.split("|")[min(choice, argument.count("|"))] for argument in arguments]
        output = io.StringIO()
        try:
            with contextlib.redirect_stderr(output), contextlib.redirect_stdout(io.StringIO()):
                parser.parse_args(chosen)
        except SystemExit as stop:
            if not stop.code:
                continue                # --help
            message = output.getvalue().strip().splitlines()[-1]
            refused = re.findall(r"'([^']*)'", message.split("error:", 1)[-1])
            if any(PLACEHOLDER.fullmatch(value) for value in refused):
                continue
            if inline and re.search(r"arguments are required|expected one argument", message):
                continue
            return message
    return None


@cache
def xvoe_parser(lenient: bool = False) -> argparse.ArgumentParser:
    """The `xvoe` command's parser; `lenient`: with no required flags, so that a mention in prose
    such as `xvoe train --stage plato` is refused for --stage, not for leaving out --out."""
    from xvoe import cli

    parser = cli.build_parser()
    if lenient:
        parsers = [parser]
        while parsers:                  # argparse keeps no public list of its actions
            for action in parsers.pop()._actions:
                if action.option_strings:
                    action.required = False
                if isinstance(action, argparse._SubParsersAction):
                    parsers += action.choices.values()
    return parser


@cache
def benchmark_flags(script: Path) -> frozenset[str]:
    """The flags a benchmark script's argparse takes: the string arguments of its add_argument calls,
    and of those in the sibling benchmark scripts it imports from (a parser built by another)."""
    flags = {"-h", "--help"}
    for node in ast.walk(ast.parse(script.read_text())):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
            flags |= {arg.value for arg in node.args
                      if isinstance(arg, ast.Constant) and str(arg.value).startswith("-")}
        elif isinstance(node, ast.ImportFrom) and node.module and (script.parent / f"{node.module}.py").exists():
            flags |= benchmark_flags(script.parent / f"{node.module}.py")
    return frozenset(flags)


def takes_flag(flags: Iterable[str], flag: str) -> bool:
    """As argparse reads it: the flag itself, or an abbreviation of exactly one."""
    return flag in flags or len([known for known in flags if known.startswith(flag)]) == 1


# ---------------------------------------------------------------------------------------------
# The checks: each takes a text and yields its dead references

PATH = re.compile(rf"(?<![\w./-])((?:{'|'.join(TOP)})/[\w./*-]*[\w*/])")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
CITATION = re.compile(r"(docs/[\w/-]+\.md),?\s+\(?\"([^\"]+)\"")     # docs/X.md, "H" or docs/X.md ("H")
NEXT_HEADING = re.compile(r"\s*(?:,\s*(?:and\s+)?|\s+and\s+)\"([^\"]+)\"")     # , "B" / and "B" / , and "B"
BARE_DOC = re.compile(r"(?<![\w./-])([A-Z][A-Z0-9_-]*\.md)\b")      # README.md, NOTES-38.md
DESIGN = re.compile(r"\bDESIGN(?:\.md)?,?\s+sections?\s+\d+(?:\.\d+)*")
API = re.compile(r"(?<![\w./-])((?:xvoe\.)?viz|xvoe)((?:\.\w+)+)(?![\w-])")


def exists(path: str, base: Path) -> bool:
    """Is `path` (relative to `base`) in the repository? A glob matches at least one file."""
    path = path.rstrip(".")
    if path.startswith(GENERATED):
        return True
    return any(base.glob(path)) if "*" in path else (base / path).exists()


def dead_paths(text: Text) -> Iterator[Dead]:
    """Paths of the repository (from its root) and markdown links (from the file that holds them)."""
    for found in PATH.finditer(text.text):
        if not exists(found.group(1), ROOT):
            yield Dead(text.at(found.start(1)), found.group(1), "no such file or directory")
    if text.code:
        return
    for found in LINK.finditer(text.text):
        target = found.group(1).split("#")[0]
        if target and not re.match(r"[a-z]+:", target) and not exists(target, text.path.parent):
            yield Dead(text.at(found.start(1)), found.group(1), f"no such file from {relative(text.path.parent)}/")
    for found in BARE_DOC.finditer(text.text):
        name = found.group(1)
        if not any((base / name).exists() for base in (ROOT, ROOT / "docs", text.path.parent)):
            yield Dead(text.at(found.start(1)), name, "no such file in the repository")
    for found in DESIGN.finditer(text.text):
        if not (ROOT / "DESIGN.md").exists():
            instead = '; cite docs/design.md, "Heading"' if (ROOT / "docs" / "design.md").exists() else ""
            yield Dead(text.at(found.start()), found.group(), f"cites DESIGN, which is not in the repository{instead}")


def headings(path: Path) -> set[str]:
    """A markdown file's headings (#, ##, ...; not in code blocks), backticks and spacing dropped."""
    prose = markdown_texts(path.read_text(), path, "")[0].text
    return {plain(row.lstrip("#")) for row in prose.split("\n") if re.match(r"#+\s", row)}


def plain(heading: str) -> str:
    return " ".join(heading.replace("`", "").split())


def nearest(heading: str, known: set[str]) -> str:
    """A hint for a dead citation: the heading it abbreviates or is closest to."""
    close = [full for full in sorted(known) if full.startswith(heading)] or difflib.get_close_matches(heading, known, 1)
    return f"; the nearest is {close[0]!r}" if close else ""


def dead_citations(text: Text) -> Iterator[Dead]:
    """Section citations `docs/NAME.md, "Heading"` and the `, "Heading"`s that follow in a list."""
    for found in CITATION.finditer(text.text):
        cited = [(found.start(2), found.group(2))]
        end = found.end()
        while more := NEXT_HEADING.match(text.text, end):
            cited.append((more.start(1), more.group(1)))
            end = more.end()
        document = ROOT / found.group(1)
        if not document.exists():
            continue                    # a dead path, reported by dead_paths
        known = headings(document)
        for offset, heading in cited:
            if not re.fullmatch(r"<[^>]*>", heading) and plain(heading) not in known:
                yield Dead(text.at(offset), f'{found.group(1)}, "{plain(heading)}"',
                           "no such heading" + nearest(plain(heading), known))


def dead_commands(text: Text) -> Iterator[Dead]:
    """`xvoe ...` lines that the command's parser refuses; flags a benchmark script does not take."""
    for offset, command, inline in commands(text):
        if " ... " in f" {command} ".replace("...]", "... "):
            continue                    # an elided command
        arguments = arguments_after(command, is_xvoe)
        if arguments is not None:
            error = parse_error(xvoe_parser(lenient=inline), arguments, inline)
            if error:
                yield Dead(text.at(offset), command, error)
        arguments = arguments_after(command, is_benchmark)
        if arguments is not None:
            script = ROOT / re.search(r"benchmarks/\w+\.py", command).group()
            if not script.exists():
                continue                # a dead path, reported by dead_paths
            for argument in arguments:
                flag = argument.strip("[]").split("=")[0]
                if flag.startswith("-") and not takes_flag(benchmark_flags(script), flag):
                    yield Dead(text.at(offset), command, f"{relative(script)} takes no {flag}")


@cache
def public_homes() -> dict[str, str]:
    """xvoe's public names -> the module each is imported from, read from the imports of
    xvoe/__init__.py's `if TYPE_CHECKING:` block, so that no name is imported to be found."""
    tree = ast.parse((ROOT / "xvoe" / "__init__.py").read_text())
    return {alias.asname or alias.name: "xvoe" + ("." + node.module if node.module else "")
            for block in tree.body if isinstance(block, ast.If) for node in block.body
            if isinstance(node, ast.ImportFrom) for alias in node.names}


@cache
def module_names(module: str) -> dict[str, str] | None:
    """What a module of the repository holds at its top level, read from its source, name ->
    "module", "function" or "other" (a class, a constant, an import); None if there is no such
    module. Read, not imported: importing every module the docs name would cost seconds."""
    base = ROOT / module.replace(".", "/")
    if not base.is_dir() and not base.with_suffix(".py").exists():
        return None
    source = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")      # a package may have none
    names = {path.stem: "module" for path in base.glob("*.py")}
    names |= {path.name: "module" for path in base.glob("*") if path.is_dir() and path.name != "__pycache__"}
    statements = list(ast.parse(source.read_text()).body) if source.exists() else []
    while statements:
        node = statements.pop()
        if isinstance(node, ast.If | ast.Try):              # `if TYPE_CHECKING:`, `try: import ...`
            statements += [*node.body, *node.orelse, *getattr(node, "finalbody", [])]
            statements += [line for handler in getattr(node, "handlers", []) for line in handler.body]
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            names[node.name] = "function"
        elif isinstance(node, ast.ClassDef):
            names[node.name] = "other"
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names |= {(alias.asname or alias.name).split(".")[0]: "other" for alias in node.names}
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {name.id: "other" for target in targets for name in ast.walk(target) if isinstance(name, ast.Name)}
    return names


def resolve(dotted: str) -> str | None:
    """Why `xvoe.a.b` names nothing, or None.

    `xvoe.NAME` is a name of the public API (found in its home module) or a subpackage; each
    further name is looked up in its module until one is not a module. A function has no
    attributes; an attribute of a class or constant is not checked.
    """
    parts = dotted.split(".")
    if parts[0] != "xvoe" or parts[1:2] == ["viz"]:
        return "there is no xvoe.viz: the figures are xvoe.plot_* and xvoe.show*, from the modules of xvoe.apps"
    module, name = public_homes().get(parts[1], "xvoe"), parts[1]
    for part in parts[2:]:
        kind = (module_names(module) or {}).get(name)
        if kind is None:
            return f"{module} has no {name}"
        if kind == "function":
            return f"{module}.{name} is a function: it has no {part}"
        if kind != "module":
            return None
        module, name = f"{module}.{name}", part
    if name not in (module_names(module) or {}):
        return f"{module} has no {name}"
    return None


def dead_names(text: Text) -> Iterator[Dead]:
    """Dotted API names: xvoe.NAME (and deeper) resolves; viz.NAME and xvoe.viz.NAME never do."""
    for found in API.finditer(text.text):
        dotted = found.group(1) + found.group(2).rstrip(".")
        if dotted.endswith((".py", ".md", ".h5", ".csv", ".pt")):
            continue                    # a file name
        why = resolve(dotted)
        if why:
            yield Dead(text.at(found.start()), dotted, why)


# Flags prose may name that belong to another program, each with its program.
OTHER_TOOLS = {"--durations": "pytest", "--dist": "pytest-xdist", "--nproc_per_node": "torchrun",
               "--standalone": "torchrun"}
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9]*(?:[-_][a-z0-9]+)*")
SCRIPTS = ("benchmarks/*.py", "tests/interruptions.py")     # the repository's scripts with flags of their own


@cache
def known_flags() -> frozenset[str]:
    """Every long option of an xvoe verb, of a script of the repository, and OTHER_TOOLS'."""
    flags, parsers = set(OTHER_TOOLS), [xvoe_parser()]
    while parsers:
        for action in parsers.pop()._actions:
            flags |= {option for option in action.option_strings if option.startswith("--")}
            if isinstance(action, argparse._SubParsersAction):
                parsers += action.choices.values()
    for pattern in SCRIPTS:
        for script in ROOT.glob(pattern):
            flags |= benchmark_flags(script)
    return frozenset(flags)


def dead_flags(text: Text) -> Iterator[Dead]:
    """`--flags` named in prose (a comment, a docstring, markdown) that nothing takes. A flag in a
    command (`xvoe ...`, `python benchmarks/X.py ...`) is its parser's to check (dead_commands)."""
    if text.code:
        return
    commands = [span.span(1) for span in INLINE_CODE.finditer(text.text)
                if arguments_after(span.group(1), is_xvoe) is not None
                or arguments_after(span.group(1), is_benchmark) is not None]
    for found in FLAG.finditer(text.text):
        inside = any(start <= found.start() < end for start, end in commands)
        if not inside and found.group() not in known_flags():
            yield Dead(text.at(found.start()), found.group(),
                       "no xvoe verb, script of the repository or tool of OTHER_TOOLS takes it")


CHECKS = (dead_paths, dead_citations, dead_commands, dead_names, dead_flags)


def dead_references(texts: Iterable[Text]) -> list[Dead]:
    return [dead for text in texts for check in CHECKS for dead in check(text)]
