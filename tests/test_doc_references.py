"""Docs that cannot rot: every dotted ``bridge.*`` / ``benchmarks.*`` name that a docstring or a
comment of the code or the tests, README.md or docs/*.md mentions is a module or an attribute
that exists, and every path of the repository they name is there.

A name resolves when its longest importable prefix is a module and each part after it is an
attribute of the one before (for a class also a declared field, or an attribute its methods
set on ``self``). A path (``bridge/app/pipeline.py``, ``docs/tools.md``) resolves when the file
or folder is in the checkout.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import io
import re
import textwrap
import tokenize
from collections.abc import Iterator
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: A dotted name of the package or the benchmarks, not part of a longer word or path
#: (``compass-bridge.service`` is a unit file, ``app/bridge.py`` a path).
NAME = re.compile(r"(?<![\w./-])(?:bridge|benchmarks)(?:\.[A-Za-z_]\w*)+")
#: A path under one of the repository's folders, as the docs write them.
PATH = re.compile(
    r"(?<![\w./-])(?:bridge|benchmarks|tests|docs|systemd|config)/[\w./*-]*[\w/*](?![\w(])"
)
#: Files named like a dotted name (``bridge.toml`` in a test's temporary directory).
FILE_SUFFIXES = ("py", "toml", "md", "json", "png", "txt", "log")


#: A string literal (any quotes; a prefix does not change where it ends) or a comment,
#: whichever starts first, so a "#" inside a string is never taken for a comment: the
#: comments ``tokenize`` finds, in a tenth of its time (a test below holds the two to the
#: same answer on awkward strings and on this module). A match is a comment when it starts
#: with "#". (The five alternatives are not wrapped in groups: each then starts with its
#: quote or "#", and ``re`` skips to the next of those characters in C instead of trying
#: the pattern at every position -- a third of the time over the ~3 MB of code.)
_STRING_OR_COMMENT = re.compile(
    r"'''[^'\\]*(?:(?:\\.|'(?!''))[^'\\]*)*'''"
    r'|"""[^"\\]*(?:(?:\\.|"(?!""))[^"\\]*)*"""'
    r"|'[^'\\\n]*(?:\\.[^'\\\n]*)*'"
    r'|"[^"\\\n]*(?:\\.[^"\\\n]*)*"'
    r"|#[^\r\n]*"
)


def _code_files() -> list[Path]:
    return sorted(
        [*ROOT.glob("bridge/**/*.py"), *ROOT.glob("benchmarks/**/*.py"), *ROOT.glob("tests/*.py")]
    )


def _doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted(ROOT.glob("docs/*.md"))]


@cache
def _scanned(source: str) -> tuple[re.Match[str], ...]:
    """The string literals and comments of ``source`` (:data:`_STRING_OR_COMMENT`), in order.

    Scanned once per module: the test reads a module's strings (:func:`_may_dangle`) and
    then its comments, and the scan of the ~3 MB of code is most of what either costs.
    """
    return tuple(_STRING_OR_COMMENT.finditer(source))


#: A string's prefix (``r``, ``b``, ``f``, ``rb`` ...), not the end of a word before a quote.
_PREFIX = re.compile(r"(?<!\w)[rRbBuUfF]{1,2}$")
#: What may stand between two string literals that Python joins into one (``"a" "b"``).
_JOINING = re.compile(r"[\s\\]*")


def _string_values(source: str) -> Iterator[str]:
    """The value of every ``str`` literal of ``source`` and of every run of adjacent ones.

    A docstring is one of them (a literal, or adjacent literals joined), so when none of
    these holds a dangling name or path, no docstring does and the module need not be
    parsed: the test then reads its comments only, in a fraction of the time (parsing
    every module is most of its cost). Escapes are decoded, so what is checked is the
    value, as for a docstring.
    """
    run: list[str] = []
    end = 0
    for m in _scanned(source):
        if m.group()[0] == "#":
            gap_end = m.start()  # a comment between two joined literals: skip it
            if not _JOINING.fullmatch(source, end, gap_end):
                run = []
            end = m.end()
            continue
        start, raw = m.start(), m.group()
        p = _PREFIX.search(source, max(0, start - 2), start)
        prefix = p.group() if p else ""
        joined = run and _JOINING.fullmatch(source, end, start - len(prefix))
        end = m.end()
        if "f" in prefix.lower() or "b" in prefix.lower():
            run = []  # an f-string or bytes: never a docstring, nor part of one
            continue
        if "\\" in raw:
            value = ast.literal_eval(prefix + raw)
        else:
            value = raw[3:-3] if len(raw) >= 6 and raw[:3] in ('"""', "'''") else raw[1:-1]
        run = [*run, value] if joined else [value]
        for i in range(len(run)):
            yield "".join(run[i:])


def _comments_of(source: str) -> Iterator[tuple[int, str]]:
    """(line, text) of every comment of ``source``."""
    line, at = 1, 0
    for m in _scanned(source):
        if m.group()[0] == "#":
            line += source.count("\n", at, m.start())
            at = m.start()
            yield line, m.group()


def _docstrings_of(source: str) -> Iterator[tuple[int, str]]:
    """(line, text) of every docstring (module, class, function) of ``source``."""
    # Docstrings hang only off statements, so walk statement bodies (a tenth of the nodes
    # ast.walk would visit: the expressions inside them are never docstrings).
    todo: list[ast.AST] = [ast.parse(source)]
    while todo:
        node = todo.pop()
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                yield body[0].lineno, body[0].value.value
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            todo += [n for n in getattr(node, field, ()) if isinstance(n, ast.AST)]


def _docstrings_and_comments_of(source: str) -> Iterator[tuple[int, str]]:
    yield from _docstrings_of(source)
    yield from _comments_of(source)


def _texts() -> Iterator[tuple[str, int, str]]:
    """(file, line, text) of everything the test reads."""
    for path in _code_files():
        rel = str(path.relative_to(ROOT))
        source = path.read_text()
        # (only a module some string of which names something missing is parsed for its
        # docstrings: see _string_values; the others could add nothing to the findings)
        read = _docstrings_and_comments_of if _may_dangle(source) else _comments_of
        for line, text in read(source):
            for i, piece in enumerate(text.splitlines()):
                yield rel, line + i, piece
    for path in _doc_files():
        rel = str(path.relative_to(ROOT))
        for i, piece in enumerate(path.read_text().splitlines(), 1):
            yield rel, i, piece


@cache
def _self_attributes(cls: type) -> frozenset[str]:
    """Attributes a class's own methods set on ``self`` (``self.truth = ...``)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):
        return frozenset()
    return frozenset(
        t.attr
        for node in ast.walk(tree)
        for t in (
            node.targets
            if isinstance(node, ast.Assign)
            else [node.target]
            if isinstance(node, ast.AnnAssign | ast.AugAssign)
            else []
        )
        if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self"
    )


def _declared(cls: type, name: str) -> bool:
    return any(
        name in getattr(c, "__annotations__", {}) or name in _self_attributes(c)
        for c in cls.__mro__
    )


@cache
def resolves(name: str) -> bool:
    """Whether ``name`` is a module, or a module's attribute chain (see the module docstring)."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        break
    else:
        return False
    for part in parts[cut:]:
        if hasattr(obj, part):
            obj = getattr(obj, part)
        elif isinstance(obj, type) and _declared(obj, part):
            obj = None  # an instance's field: nothing further to follow on the class
        else:
            return False
    return True


def _missing(text: str) -> tuple[list[str], list[str]]:
    """The dangling names and the missing paths ``text`` (one line) mentions."""
    names: list[str] = []
    paths: list[str] = []
    # A name holds "bridge" or "benchmarks", a path a "/": a pattern is not tried on a line
    # without them (~9 in 10 lines have neither; the patterns cost a step per character).
    if "bridge" in text or "benchmarks" in text:
        for m in NAME.finditer(text):
            name = m.group(0)
            if name.rsplit(".", 1)[-1] not in FILE_SUFFIXES and not resolves(name):
                names.append(name)
    if "/" not in text:
        return names, paths
    for m in PATH.finditer(text):
        path = m.group(0).rstrip(".")
        if "*" not in path and "<" not in path and not (ROOT / path).exists():
            paths.append(path)
    return names, paths


def _may_dangle(source: str) -> bool:
    """Whether a string of ``source`` (so perhaps a docstring) names something missing."""
    try:
        return any(
            any(_missing(piece)) for value in _string_values(source) for piece in value.splitlines()
        )
    except (ValueError, SyntaxError):  # a literal the scanner misread: parse the module
        return True


@cache  # both tests read the same texts: parse and tokenize the tree once
def _dangling() -> tuple[list[str], list[str]]:
    names, paths = [], []
    for file, line, text in _texts():
        bad_names, bad_paths = _missing(text)
        names += [f"{file}:{line}: {name}" for name in bad_names]
        paths += [f"{file}:{line}: {path}" for path in bad_paths]
    return names, paths


def test_every_dotted_name_in_docstrings_comments_and_docs_exists() -> None:
    names, _ = _dangling()
    assert not names, "names that no longer exist:\n" + "\n".join(names)


def test_every_repository_path_in_docstrings_comments_and_docs_exists() -> None:
    _, paths = _dangling()
    assert not paths, "paths that are not in the checkout:\n" + "\n".join(paths)


def test_the_resolver_tells_a_real_name_from_a_dangling_one() -> None:
    assert resolves("bridge.app.pipeline.Pipeline.on_frame")  # a method
    assert resolves("bridge.sim.firmware.Firmware.truth")  # set on self in __init__
    assert resolves("bridge.protocol.device.Received.frame")  # a field
    assert resolves("benchmarks.pipeline")
    assert not resolves("bridge.daemon.CompassSample")  # moved to bridge.app.sample
    assert not resolves("bridge.ports.DevicePort")  # a module that is gone
    assert not resolves("bridge.app.pipeline.Pipeline.no_such_member")
    found = [m.group(0) for m in NAME.finditer("compass-bridge.service, see bridge.events.")]
    assert found == ["bridge.events"]


#: Strings that hold "#", quotes of the other kind and escaped quotes (one line each).
AWKWARD = "\n".join(
    [
        r'a = "# not a comment"  # one',
        r"b = '\'#'  # two: an escaped quote, then a hash in the string",
        r'c = """',
        r"# not a comment either",
        "\"'\"\"\" + '''x # \"'''  # three",
        r'd = rb"\\" + f"{a!r}#{b}"  # four',
        "e = ''  # five ''' still the comment",
        r"#six",
        "",
    ]
)


def test_the_comment_scanner_finds_what_tokenize_finds() -> None:
    for source in (AWKWARD, Path(__file__).read_text()):
        tokens = tokenize.generate_tokens(io.StringIO(source).readline)
        want = [(t.start[0], t.string) for t in tokens if t.type == tokenize.COMMENT]
        got = [(n, text) for n, text in _docstrings_and_comments_of(source) if text[:1] == "#"]
        assert got == want
        assert not [c for _, c in got if "not a comment" in c]
    assert len(want) > 10


#: Docstrings written as a scanner could misread them: an escape that makes the name,
#: literals Python joins (a comment between), a raw string, a newline escape before it.
PLANTED = r'''
def a():
    """See bridge.nope_a."""


def b():
    "See \x62ridge.nope_b, decoded."


class C:
    ("See bridge."  # a comment between
     "nope_c")


def d():
    r"""Raw \d and bridge.nope_d."""


def e():
    u'x\nbridge.nope_e'


def f():
    x = "bridge.nope_f"  # a string, not a docstring: never reported
'''


def test_only_modules_whose_strings_name_nothing_missing_skip_the_docstring_parse() -> None:
    # every docstring is among the string values the shortcut reads, so skipping the parse
    # of a module none of whose strings names anything missing hides nothing
    for source in (PLANTED, Path(__file__).read_text(), (ROOT / "bridge/cli.py").read_text()):
        values = set(_string_values(source))
        docs = [text for _, text in _docstrings_of(source)]
        assert docs and all(d in values for d in docs)
    found = sorted(
        name
        for _, text in _docstrings_of(PLANTED)
        for piece in text.splitlines()
        for name in _missing(piece)[0]
    )
    assert found == [f"bridge.nope_{c}" for c in "abcde"]
    assert _may_dangle(PLANTED) and not _may_dangle((ROOT / "bridge/cli.py").read_text())
