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
#: same answer on awkward strings and on this module).
_STRING_OR_COMMENT = re.compile(
    r"(?P<string>'''[^'\\]*(?:(?:\\.|'(?!''))[^'\\]*)*'''"
    r'|"""[^"\\]*(?:(?:\\.|"(?!""))[^"\\]*)*"""'
    r"|'[^'\\\n]*(?:\\.[^'\\\n]*)*'"
    r'|"[^"\\\n]*(?:\\.[^"\\\n]*)*")'
    r"|(?P<comment>#[^\r\n]*)"
)


def _code_files() -> list[Path]:
    return sorted(
        [*ROOT.glob("bridge/**/*.py"), *ROOT.glob("benchmarks/**/*.py"), *ROOT.glob("tests/*.py")]
    )


def _doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted(ROOT.glob("docs/*.md"))]


def _docstrings_and_comments(path: Path) -> Iterator[tuple[int, str]]:
    """(line, text) of every docstring (module, class, function) and comment of a module."""
    yield from _docstrings_and_comments_of(path.read_text())


def _docstrings_and_comments_of(source: str) -> Iterator[tuple[int, str]]:
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
    line, at = 1, 0
    for m in _STRING_OR_COMMENT.finditer(source):
        if m.lastgroup == "comment":
            line += source.count("\n", at, m.start())
            at = m.start()
            yield line, m.group()


def _texts() -> Iterator[tuple[str, int, str]]:
    """(file, line, text) of everything the test reads."""
    for path in _code_files():
        rel = str(path.relative_to(ROOT))
        for line, text in _docstrings_and_comments(path):
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


@cache  # both tests read the same texts: parse and tokenize the tree once
def _dangling() -> tuple[list[str], list[str]]:
    names, paths = [], []
    for file, line, text in _texts():
        for m in NAME.finditer(text):
            name = m.group(0)
            if name.rsplit(".", 1)[-1] in FILE_SUFFIXES:
                continue
            if not resolves(name):
                names.append(f"{file}:{line}: {name}")
        for m in PATH.finditer(text):
            path = m.group(0).rstrip(".")
            if "*" in path or "<" in path:
                continue
            if not (ROOT / path).exists():
                paths.append(f"{file}:{line}: {path}")
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
    assert resolves("bridge.device.Received.frame")  # a field
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
