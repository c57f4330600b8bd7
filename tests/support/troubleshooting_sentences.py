"""The sentences a user of repetrel-host can read when something goes wrong, collected
from the source with ``ast`` (for tests/test_troubleshooting.py, which checks that
docs/troubleshooting.md explains each of them, and quotes none that is gone).

What counts (a *sink* is a call whose text reaches a user):

- an exception built with a message, raised or handed on (``job.stop(JobError(...))``):
  the package's own classes (HostError's family, the server's ``Refused``...), the
  built-in ones, ``HTTPException``'s detail, ``pytest.UsageError``; less the few in
  ``EXCLUDED`` below, which no user sees;
- the calls that carry a failure's or a warning's sentence to the user: a dialect's
  ``_fail(kind, reason)``, the ``Failed``/``LineRefused``/``Notice`` events (the CLI prints
  a notice as ``warning:``), the lint's ``Finding``, ``hyrel-server``'s ``fail``,
  ``pytest.fail``/``pytest.skip``/``pytest.exit``, an HTTP error's JSON body;
- a line printed with an ``error:``, ``not safe:`` or ``warning:`` prefix of its own, or
  starting with a refusal's words (``no snapshot``, ``refused``), or printed in an
  ``except`` block (an error path: "interrupted before streaming began.");
- a function of the package whose parameter goes into a sink is a sink too (found by
  following the calls within a module; ``SINK_METHODS`` names the few called through an
  object that another module holds), and a message held in a name (a local variable,
  a module's constant) or returned by a helper of the package (``describe_open_error``)
  is followed to its strings. What a function found to be a sink is given, and the text
  of a variable put into a message, are *fragments*: the page quotes them inside the
  sentence they go into (a fragment of fewer than four words is a value, not a sentence).

An f-string's ``{...}`` becomes a placeholder; a message made of placeholders only (a
relayed ``str(exc)``) says nothing of its own and is left out, as is one without
a word of three letters (``M{code}``). Excluded classes: ``EXCLUDED_CLASSES``.
"""

from __future__ import annotations

import ast
import builtins
import functools
import itertools
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.support.paths import ROOT

SRC = ROOT / "src" / "repetrel_host"

# Calls that carry a user's sentence, by the callee's last name: which arguments hold it
# (None: every string-like argument).
SINK_CALLS: dict[str, int | None] = {
    "Finding": 2,  # the lint's finding: Finding(line, severity, message)
    "DialectFailed": 1,  # a dialect's failure event: DialectFailed(kind, reason, tag)
    "LineRefused": 0,  # a line the controller refused: LineRefused(reason, tag)
    "Notice": 0,  # printed as "warning: ..."
    "fail": None,  # pytest.fail
    "skip": None,  # pytest.skip: why a hardware test did not run
    "exit": None,  # pytest.exit
}
# Functions of one module whose argument is a user's sentence (module, name, index).
SINK_FUNCTIONS = {
    ("server/settings.py", "fail", 0),  # "hyrel-server: ..." on stderr, exit 2
    ("server/main.py", "fail", 0),  # the same, imported
    # The dialects' failure, defined with the reading of replies (reprap_replies,
    # hyrel_replies).
    ("protocol/dialects/reprap.py", "_fail", 1),
    ("protocol/dialects/hyrel.py", "_fail", 1),
}
# Methods whose argument goes into a user's sentence, called on an object that other
# modules hold (the calls followed are a module's own or its imports'): the session's parts
# give up on the owed safe stop through the part that owns it (owed.py), for a reason.
SINK_METHODS = {("session/owed.py", "give_up", 0)}
# Third-party exception classes whose message a user reads.
FOREIGN_ERRORS = {"HTTPException": 1, "UsageError": 0, "BadParameter": 0}
# Calls that print a line: those printed with an error prefix of their own count.
PRINTS = {"print", "say", "show", "echo", "write"}
PREFIXES = ("error: ", "not safe: ", "warning: ", "link failure: ", "controller error: ")
PRINTED_ERRORS = ("no snapshot", "refused", "giving up")
_MARKUP = re.compile(r"\[/?(bold|dim|yellow|red|green| )*\]")  # rich's [bold yellow]...[/]
FRAGMENT_WORDS = 4  # a piece of a sentence shorter than this is a value put into it
# The keys of an HTTP error's JSON body that hold its sentence.
BODY_KEYS = {"error", "detail"}

# Built with a message, but no user reads it: (file, the message's start, why).
EXCLUDED: list[tuple[str, str, str]] = [
    ("session/header.py", "not a number", "an invariant: the models hold numbers only"),
    ("protocol/flow.py", "rx_buffer must", "the CLI (min=2) and the models (ge=2) check first"),
    ("protocol/flow.py", "max_lines must", "the CLI (min=1) and the models (ge=1) check first"),
    ("protocol/dialects/reprap.py", "line_number_limit", "a library argument, never a user's"),
    ("protocol/dialects/reprap.py", "the dialect was already", "the session starts it once"),
    ("protocol/dialects/hyrel.py", "the dialect was already", "the session starts it once"),
    ("protocol/dialects/reprap.py", "M110 sets line numbers", "jobs and commands drop it first"),
    ("protocol/dialects/hyrel.py", "M110 sets line numbers", "jobs and commands drop it first"),
]
# Exception classes that carry no user's sentence: (class, why).
EXCLUDED_CLASSES = {
    "AssertionError": "an invariant: a bug, not a user's error",
    "LeaseLost": "the farm's own signal between its parts (its text is a node's name)",
    "StopIteration": "control flow",
    "KeyboardInterrupt": "control flow",
}

_WORD = re.compile(r"[A-Za-z]{3,}")
_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


@dataclass(frozen=True)
class Sentence:
    """A message: its fixed texts, with a placeholder between each two."""

    fixed: tuple[str, ...]
    names: tuple[str, ...]  # a name for each placeholder, for the paste form
    where: str = field(compare=False)  # file:line
    # A piece of a sentence (a variable's text, a helper's) rather than a whole one: the
    # page quotes it inside the sentence it goes into.
    fragment: bool = field(default=False, compare=False)

    @property
    def key(self) -> tuple[str, ...]:
        return tuple(" ".join(part.split()) for part in self.fixed)

    def pattern(self) -> re.Pattern[str]:
        """Matches the sentence as the page may quote it: a placeholder is any text (even
        none), whitespace any whitespace."""
        out = []
        for part in self.fixed:
            words = r"\s+".join(map(re.escape, part.split()))
            lead = r"\s*" if part[:1].isspace() else ""
            trail = r"\s*" if part[-1:].isspace() else ""
            out.append(lead + words + trail)
        return re.compile(".*?".join(out), re.DOTALL)

    def paste(self) -> str:
        """The sentence with its placeholders in capitals, as the page writes them."""
        text = self.fixed[0]
        for name, part in zip(self.names, self.fixed[1:], strict=True):
            text += name + part
        return " ".join(text.split())


@dataclass
class _Module:
    path: Path
    name: str  # relative to SRC
    tree: ast.Module
    constants: dict[str, ast.expr]
    functions: dict[str, list[ast.FunctionDef | ast.AsyncFunctionDef]]
    imported: dict[str, str]  # a name imported from another of the package's modules: its name


def _modules(root: Path) -> list[_Module]:
    modules = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        constants: dict[str, ast.expr] = {}
        for node in tree.body:
            if isinstance(node, ast.Assign) and len(node.targets) == 1:
                target = node.targets[0]
                if isinstance(target, ast.Name):
                    constants[target.id] = node.value
            elif (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and node.value is not None
            ):
                constants[node.target.id] = node.value
        functions: dict[str, list[ast.FunctionDef | ast.AsyncFunctionDef]] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                functions.setdefault(node.name, []).append(node)
        imported = {
            alias.asname or alias.name: node.module.removeprefix("repetrel_host.").replace(".", "/")
            + ".py"
            for node in tree.body
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("repetrel_host.")
            for alias in node.names
        }
        name = path.relative_to(root).as_posix()
        modules.append(_Module(path, name, tree, constants, functions, imported))
    return modules


def _exception_classes(modules: list[_Module]) -> set[str]:
    """The package's exception classes (by name), and the built-in ones."""
    known = {
        name
        for name, value in vars(builtins).items()
        if isinstance(value, type) and issubclass(value, BaseException)
    }
    known |= {"HostError"}
    classes = [
        node
        for module in modules
        for node in ast.walk(module.tree)
        if isinstance(node, ast.ClassDef)
    ]
    grew = True
    while grew:
        grew = False
        for node in classes:
            bases = {_last_name(base) for base in node.bases}
            if node.name not in known and bases & known:
                known.add(node.name)
                grew = True
    return known


def _last_name(node: ast.expr) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return ""


def _placeholder_name(node: ast.expr) -> str:
    """A capitalised name for a placeholder: ``{self.port}`` -> PORT, ``{len(errors)}`` -> N."""
    if isinstance(node, ast.Call) and _last_name(node.func) == "len":
        return "N"
    names = _IDENT.findall(ast.unparse(node))
    names = [n for n in names if n not in {"self", "str", "repr", "exc", "join", "get"}]
    return (names[-1] if names else "VALUE").upper().strip("_") or "VALUE"


Template = tuple[tuple[str, ...], tuple[str, ...]]  # fixed texts, placeholder names
_UNKNOWN: list[Template] = []


def _hole(node: ast.expr) -> Template:
    return ("", ""), (_placeholder_name(node),)


def _join(left: Template, right: Template) -> Template:
    fixed = (*left[0][:-1], left[0][-1] + right[0][0], *right[0][1:])
    return fixed, left[1] + right[1]


class _Reader:
    """Turns a message's expression into the templates it can take."""

    def __init__(self, modules: list[_Module]) -> None:
        self.modules = {m.name: m for m in modules}
        self._scopes: dict[int, dict[str, tuple[list[ast.expr], list[ast.expr]]]] = {}
        self.constants: dict[str, ast.expr] = {}
        for module in modules:
            for name, value in module.constants.items():
                if name.isupper():
                    self.constants.setdefault(name, value)

    def templates(
        self, node: ast.expr, module: _Module, scope: ast.AST | None, depth: int = 0
    ) -> list[Template]:
        """The texts ``node`` may be; an empty list when it is no string of ours."""
        if depth > 4:
            return _UNKNOWN
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return [((node.value,), ())]
        if isinstance(node, ast.JoinedStr):
            out: Template = (("",), ())
            for value in node.values:
                if isinstance(value, ast.Constant):
                    out = _join(out, ((str(value.value),), ()))
                else:
                    assert isinstance(value, ast.FormattedValue)
                    out = _join(out, _hole(value.value))
            return [out]
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
            left = self.templates(node.left, module, scope, depth + 1) or [_hole(node.left)]
            right = self.templates(node.right, module, scope, depth + 1) or [_hole(node.right)]
            if all(not t[0][0] and len(t[0]) == 2 for t in left + right):
                return _UNKNOWN  # two unknowns added: not a string of ours
            return [_join(a, b) for a, b in itertools.product(left, right)]
        if isinstance(node, ast.IfExp):
            body = self.templates(node.body, module, scope, depth + 1)
            orelse = self.templates(node.orelse, module, scope, depth + 1)
            return body + orelse
        if isinstance(node, ast.Name):
            return self._name(node.id, module, scope, depth)
        if isinstance(node, ast.Call):
            return self._helper(node, module, depth)
        return _UNKNOWN

    def _name(
        self, name: str, module: _Module, scope: ast.AST | None, depth: int
    ) -> list[Template]:
        if scope is not None:
            assigned, added = self._assignments(scope).get(name, ([], []))
            if assigned:
                out: list[Template] = []
                for value in assigned:
                    bases = self.templates(value, module, scope, depth + 1)
                    out += bases
                    for base, more in itertools.product(bases, added):
                        for extra in self.templates(more, module, scope, depth + 1):
                            out.append(_join(base, extra))
                return out
        value = module.constants.get(name) or self.constants.get(name)
        if value is not None:
            return self.templates(value, module, None, depth + 1)
        return _UNKNOWN

    def _assignments(self, scope: ast.AST) -> dict[str, tuple[list[ast.expr], list[ast.expr]]]:
        """A function's ``name = ...`` and ``name += ...``, by name."""
        found = self._scopes.get(id(scope))
        if found is None:
            found = self._scopes[id(scope)] = {}
            for node in ast.walk(scope):
                if isinstance(node, ast.Assign):
                    for target in node.targets:
                        if isinstance(target, ast.Name):
                            found.setdefault(target.id, ([], []))[0].append(node.value)
                elif isinstance(node, ast.AugAssign) and isinstance(node.target, ast.Name):
                    found.setdefault(node.target.id, ([], []))[1].append(node.value)
        return found

    def _helper(self, call: ast.Call, module: _Module, depth: int) -> list[Template]:
        """What a helper of the package returns (describe_open_error, _describe...)."""
        name = _last_name(call.func)
        places = [module] + [m for m in self.modules.values() if m is not module]
        for place in places:
            for function in place.functions.get(name, []):
                out: list[Template] = []
                for node in ast.walk(function):
                    if isinstance(node, ast.Return) and node.value is not None:
                        out += self.templates(node.value, place, function, depth + 1)
                if out:
                    return out
        return _UNKNOWN


@dataclass(frozen=True)
class _Place:
    """Where a call is: its module, the function it is in (None: the module's level), and
    whether it is in an ``except`` block (an error path)."""

    module: _Module
    scope: ast.FunctionDef | ast.AsyncFunctionDef | None
    handling: bool


def _calls(module: _Module) -> Iterator[tuple[ast.Call, _Place]]:
    def walk(node: ast.AST, place: _Place) -> Iterator[tuple[ast.Call, _Place]]:
        for child in ast.iter_child_nodes(node):
            inner = place
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                inner = _Place(module, child, False)
            elif isinstance(child, ast.ExceptHandler):
                inner = _Place(module, place.scope, True)
            if isinstance(child, ast.Call):
                yield child, inner
            yield from walk(child, inner)

    yield from walk(module.tree, _Place(module, None, False))


def _parameters(function: ast.FunctionDef | ast.AsyncFunctionDef) -> list[ast.arg]:
    args = function.args.posonlyargs + function.args.args
    return args[1:] if [a.arg for a in args[:1]] in (["self"], ["cls"]) else args


def _assigned(name: str, scope: ast.AST, reader: _Reader) -> bool:
    return bool(reader._assignments(scope).get(name, ([], []))[0])


@functools.cache
def collect(root: Path = SRC) -> list[Sentence]:
    """Every sentence a user may read, in source order (duplicates kept: each its site)."""
    modules = _modules(root)
    reader = _Reader(modules)
    errors = _exception_classes(modules) - set(EXCLUDED_CLASSES)
    sinks = SINK_FUNCTIONS | SINK_METHODS
    calls = [found for module in modules for found in _calls(module)]
    while True:  # a function whose parameter goes into a sink is one: until none is new
        found: list[Sentence] = []
        new: set[tuple[str, str, int]] = set()
        for call, place in calls:
            module = place.module
            args, passed = _message_args(call, module, errors, sinks)
            for arg in args:  # what a function found to be a sink is given: a piece
                found += _read(arg, call, place, reader, new, fragment=passed)
            found += _printed(call, place, reader)
        if not new - sinks:
            break
        sinks |= new
    return found


def _read(
    arg: ast.expr,
    call: ast.Call,
    place: _Place,
    reader: _Reader,
    new: set[tuple[str, str, int]],
    fragment: bool,
) -> list[Sentence]:
    """The sentences of one message argument, and of the pieces it is made of: a local
    variable's texts, a helper's (each a fragment of the sentence); a parameter of the
    function it is in makes that function a sink."""
    where = f"{place.module.name}:{call.lineno}"
    scope = place.scope
    out: list[Sentence] = []
    parameters = _parameters(scope) if scope is not None else []
    names = [p.arg for p in parameters]
    if isinstance(arg, ast.Name) and arg.id in names and not _assigned(arg.id, scope, reader):  # type: ignore[arg-type]
        assert scope is not None
        new.add((place.module.name, scope.name, names.index(arg.id)))
        return out
    for fixed, holes in reader.templates(arg, place.module, scope):
        out += _sentences(fixed, holes, where, fragment)
    for hole in _holes(arg):
        if isinstance(hole, ast.Name) and hole.id in names and scope is not None:
            parameter = parameters[names.index(hole.id)]
            if parameter.annotation is not None and ast.unparse(parameter.annotation) == "str":
                new.add((place.module.name, scope.name, names.index(hole.id)))
        elif isinstance(hole, ast.Name | ast.Call):
            for fixed, holes in reader.templates(hole, place.module, scope):
                out += _sentences(fixed, holes, where, fragment=True)
    return out


def _holes(node: ast.expr) -> Iterator[ast.expr]:
    """The expressions a message's text is made of: an f-string's ``{...}``, the sides of
    a ``+``, an ``if``'s branches (a call's arguments, as ``escape(...)``'s, inside)."""
    if isinstance(node, ast.JoinedStr):
        for value in node.values:
            if isinstance(value, ast.FormattedValue):
                yield from _holes(value.value)
    elif isinstance(node, ast.BinOp):
        yield from _holes(node.left)
        yield from _holes(node.right)
    elif isinstance(node, ast.IfExp):
        yield from _holes(node.body)
        yield from _holes(node.orelse)
    elif isinstance(node, ast.Call) and _last_name(node.func) in {"escape", "str"}:
        for arg in node.args:
            yield from _holes(arg)
    else:
        yield node


def _message_args(
    call: ast.Call, module: _Module, errors: set[str], sinks: set[tuple[str, str, int]]
) -> tuple[list[ast.expr], bool]:
    """The arguments of ``call`` that hold a user's sentence, if it is a sink; and whether
    it is a function found to be one (what it is given is a piece of a sentence)."""
    name = _last_name(call.func)
    keywords = {k.arg: k.value for k in call.keywords if k.arg is not None}
    if name in FOREIGN_ERRORS and name not in errors:
        index = FOREIGN_ERRORS[name]
        args = call.args[index : index + 1] or [
            v for k, v in keywords.items() if k in ("detail", "message")
        ]
        return [*args, *_body(args)], False
    if name in errors or _same_type(call):
        return [*call.args, *_body(call.args)], False
    if name == "JSONResponse":
        return _body([*call.args, *keywords.values()]), False
    # Every parameter of the function that is a sink (not the first one a set's order
    # gives: which one that is changed with the hash seed).
    method = isinstance(call.func, ast.Attribute)
    matched = sorted(
        sink
        for sink in sinks
        if sink[1] == name
        and (
            sink[0] == module.name
            or module.imported.get(name) == sink[0]
            or (method and sink in SINK_METHODS)
        )
    )
    if matched:
        args = [arg for _, _, index in matched for arg in call.args[index : index + 1]]
        return args, any(sink not in SINK_FUNCTIONS for sink in matched)
    if name in SINK_CALLS:
        index = SINK_CALLS[name]
        if name in {"fail", "skip", "exit"} and ast.unparse(call.func) != f"pytest.{name}":
            return [], False
        return (list(call.args) if index is None else call.args[index : index + 1]), False
    return [], False


def _same_type(call: ast.Call) -> bool:
    """``type(error)(f"{error}; ...")``: an error said again, longer, as its own kind."""
    func = call.func
    return isinstance(func, ast.Call) and _last_name(func.func) == "type"


def _body(args: list[ast.expr]) -> list[ast.expr]:
    """The sentences of an HTTP error's JSON body ({"error": ...} or {"detail": ...})."""
    out: list[ast.expr] = []
    for arg in args:
        if isinstance(arg, ast.Dict):
            for key, value in zip(arg.keys, arg.values, strict=True):
                if isinstance(key, ast.Constant) and key.value in BODY_KEYS:
                    out.append(value)
    return out


def _printed(call: ast.Call, place: _Place, reader: _Reader) -> list[Sentence]:
    """A line printed with an error's prefix (the sentence after it), or starting with a
    refusal's words, or printed while handling an error."""
    if _last_name(call.func) not in PRINTS or not call.args:
        return []
    out = []
    where = f"{place.module.name}:{call.lineno}"
    for fixed, names in reader.templates(call.args[0], place.module, place.scope):
        # As rich shows it: its tags gone, an escaped bracket (\[host]) a bracket.
        fixed = tuple(_MARKUP.sub("", part).replace("\\[", "[") for part in fixed)
        head = fixed[0]
        prefix = next((p for p in PREFIXES if head.startswith(p)), None)
        if prefix is not None:
            out += _sentences((head[len(prefix) :], *fixed[1:]), names, where)
        elif head.startswith(PRINTED_ERRORS) or place.handling:
            out += _sentences(fixed, names, where)
    return out


def _sentences(
    fixed: tuple[str, ...], names: tuple[str, ...], where: str, fragment: bool = False
) -> list[Sentence]:
    """The sentence, unless it has no word of its own (a relayed message, a code)."""
    if not any(_WORD.search(part) for part in fixed):
        return []
    if fragment and len(re.findall(r"\S*[A-Za-z]\S*", " ".join(fixed))) < FRAGMENT_WORDS:
        return []  # a value put into a sentence ("amount", "marlin"), not a piece of one
    return [Sentence(fixed, names, where, fragment)]


def _excluded(sentence: Sentence) -> bool:
    return any(excludes(rule, sentence) for rule in EXCLUDED)


def excludes(rule: tuple[str, str, str], sentence: Sentence) -> bool:
    path, start, _why = rule
    return sentence.where.split(":")[0] == path and sentence.paste().startswith(start)


def shown(sentences: list[Sentence]) -> list[Sentence]:
    """Less those that no user sees (``EXCLUDED``)."""
    return [s for s in sentences if not _excluded(s)]


def unique(sentences: list[Sentence]) -> list[Sentence]:
    """One of each (the first site)."""
    seen: dict[tuple[str, ...], Sentence] = {}
    for sentence in sentences:
        seen.setdefault(sentence.key, sentence)
    return list(seen.values())


if __name__ == "__main__":
    everything = shown(collect())
    for sentence in unique(everything):
        print(f"{sentence.where}\t{sentence.paste()}")
    print(f"{len(everything)} sites, {len(unique(everything))} sentences")
