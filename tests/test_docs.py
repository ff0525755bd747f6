"""The executor's documentation holds: its engine's stub says what the C provides, its module tables name every module.

Read from the sources, without building or importing anything: the C
extension's tables (``fastpath/*.c``) against its stub (``_fastpath.pyi``),
and the files of ``container/executor/`` against the module table of
``docs/executor/routes.md`` and the layout in ``CONTRIBUTING.md``.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field
from typing import TypeVar

import pytest

from tests.container_support import REPO

EXECUTOR = REPO / "container" / "executor"
FASTPATH = EXECUTOR / "fastpath"
STUB = EXECUTOR / "_fastpath.pyi"
ROUTES = REPO / "docs" / "executor" / "routes.md"
CONTRIBUTING = REPO / "CONTRIBUTING.md"
#: The pure-Python engine, a package being written beside the C: not failed for while it is absent.
PYENGINE = "_pyengine/"

T = TypeVar("T")

# -- the C side -------------------------------------------------------------------------------------

#: Type slots that give a Python name of their own (``__init__`` is told apart below).
DUNDER_SLOTS = {
    "tp_init": "__init__",
    "tp_call": "__call__",
    "tp_iter": "__iter__",
    "tp_iternext": "__next__",
    "sq_length": "__len__",
    "sq_contains": "__contains__",
    "mp_length": "__len__",
    "mp_subscript": "__getitem__",
    "nb_bool": "__bool__",
}

_TABLE = re.compile(r"\bPy(MethodDef|MemberDef|GetSetDef)\s+(\w+)\s*\[\]\s*=\s*\{(.*?)\n\};", re.DOTALL)
#: An entry of a table: ``{"name", ...``; the rest of the entry up to the next one.
_ENTRY = re.compile(r"\{\s*\"([A-Za-z_]\w*)\"\s*,(.*?)(?=\{\s*\"[A-Za-z_]|\{\s*NULL|\Z)", re.DOTALL)
_TYPE = re.compile(r"\bPyTypeObject\s+(\w+)\s*=\s*\{(.*?)\n\};", re.DOTALL)
_FIELD = re.compile(r"\.(\w+)\s*=\s*([^,\n]+)")
_SLOT_TABLE = re.compile(r"\bPy(?:Sequence|Mapping|Number)Methods\s+(\w+)\s*=\s*\{(.*?)\n\};", re.DOTALL)


@dataclass
class Api:
    """One side's names: module functions, int constants, and each class's members."""

    #: Where each name was found, for the messages.
    functions: dict[str, str] = field(default_factory=dict)
    constants: dict[str, str] = field(default_factory=dict)
    #: Class -> where it was found.
    classes: dict[str, str] = field(default_factory=dict)
    #: Class -> member -> "method" or "attribute".
    members: dict[str, dict[str, str]] = field(default_factory=dict)
    #: Class -> attribute -> whether it can be set.
    settable: dict[str, dict[str, bool]] = field(default_factory=dict)


def c_sources() -> dict[str, str]:
    """Each C source of the extension by file name."""
    return {path.name: path.read_text(encoding="utf-8") for path in sorted(FASTPATH.glob("*.c"))}


def _entries(body: str) -> list[tuple[str, str]]:
    """Each entry of a table's initialiser: its name, and the rest of the entry."""
    found: list[tuple[str, str]] = _ENTRY.findall(body)
    return found


def _lookup(found: dict[str, T], key: str, what: str) -> T:
    """``found[key]``, or a failure that says which definition the parser missed."""
    if key not in found:
        pytest.fail(f"fastpath/*.c: {what} {key} is used, but no definition of it was found (the parser's regexes)")
    return found[key]


def _function_body(sources: dict[str, str], name: str) -> str:
    """The text of C function ``name`` (up to its closing brace at the start of a line)."""
    for text in sources.values():
        found = re.search(rf"^[\w \*]*\b{re.escape(name)}\s*\([^;{{]*\)\s*\{{(.*?)^\}}", text, re.DOTALL | re.MULTILINE)
        if found:
            return found.group(1)
    return ""


def c_api(sources: dict[str, str]) -> Api:
    """What ``PyInit__fastpath`` (in ``module.c``) registers, read from the tables of ``sources``."""
    module = sources["module.c"]
    tables: dict[str, tuple[str, str, str]] = {}  # table -> (kind, body, file)
    slot_tables: dict[str, str] = {}
    types: dict[str, tuple[dict[str, str], str]] = {}  # C variable -> (its fields, file)
    for file, text in sources.items():
        for kind, name, body in _TABLE.findall(text):
            tables[name] = (kind, body, file)
        for name, body in _SLOT_TABLE.findall(text):
            slot_tables[name] = body
        for name, body in _TYPE.findall(text):
            types[name] = ({key: value.strip() for key, value in _FIELD.findall(body)}, file)
    api = Api()
    init = module[module.index("PyInit__fastpath") :]
    function_tables = re.findall(r"\.m_methods\s*=\s*(\w+)", module) + re.findall(
        r"PyModule_AddFunctions\(\s*\w+\s*,\s*(\w+)\s*\)", init
    )
    for table in function_tables:
        _, body, file = _lookup(tables, table, "the function table")
        for name, _ in _entries(body):
            api.functions[name] = f"{file} ({table})"
    constants = re.findall(r"PyModule_AddIntConstant\(\s*\w+\s*,\s*\"(\w+)\"", init)
    for name in [*constants, *re.findall(r"PyModule_AddIntMacro\(\s*\w+\s*,\s*(\w+)\s*\)", init)]:
        api.constants[name] = "module.c (PyInit__fastpath)"
    # Types registered by name ({"Notifier", &NotifierType}) or by PyModule_AddType (named by tp_name).
    registered = re.findall(r"\{\s*\"(\w+)\"\s*,\s*&(\w+)\s*\}", init)
    for variable in re.findall(r"PyModule_AddType\(\s*\w+\s*,\s*&(\w+)\s*\)", init):
        tp_name = _lookup(types, variable, "the type")[0].get("tp_name", "")
        registered.append((tp_name.strip('"').rpartition(".")[2], variable))
    for name, variable in registered:
        fields, file = _lookup(types, variable, "the type")
        api.classes[name] = f"{file} ({variable})"
        members = api.members[name] = {}
        settable = api.settable[name] = {}
        for slot in ("tp_methods", "tp_members", "tp_getset"):
            table = fields.get(slot)
            if table is None:
                continue
            kind, body, _ = _lookup(tables, table, "the table")
            for member, rest in _entries(body):
                before_doc = rest.split('"')[0]
                if kind == "MethodDef":
                    members[member] = "method"
                elif kind == "MemberDef":  # {name, type, offset, flags, doc}
                    members[member] = "attribute"
                    settable[member] = re.search(r"\bREADONLY\b", before_doc) is None
                else:  # GetSetDef: {name, getter, setter, doc, closure}
                    members[member] = "attribute"
                    settable[member] = before_doc.split(",")[1].strip() not in ("NULL", "0")
        slots = dict(fields)
        for slot in ("tp_as_sequence", "tp_as_mapping", "tp_as_number"):
            if slot in fields:
                slots.update(_FIELD.findall(_lookup(slot_tables, fields[slot].lstrip("&"), "the slot table")))
        for slot, dunder in DUNDER_SLOTS.items():
            if slot in slots:
                members[dunder] = "method"
        # A constructor that takes arguments in tp_new (no tp_init) is __init__ to Python.
        new = fields.get("tp_new", "PyType_GenericNew")
        if new != "PyType_GenericNew" and "PyArg_Parse" in _function_body(sources, new):
            members["__init__"] = "method"
    return api


# -- the stub ---------------------------------------------------------------------------------------

#: Classes of the stub that only describe types for checkers (no runtime object of the engine).
_TYPING_BASES = {"Protocol", "TypedDict"}


def _decorators(node: ast.FunctionDef) -> set[str]:
    names = set()
    for decorator in node.decorator_list:
        if isinstance(decorator, ast.Name):
            names.add(decorator.id)
        elif isinstance(decorator, ast.Attribute):
            names.add(decorator.attr)  # ``@x.setter``
    return names


def stub_api(text: str) -> Api:
    """What a stub (``_fastpath.pyi``'s ``text``) declares."""
    tree = ast.parse(text)
    api = Api()
    for node in tree.body:
        where = f"_fastpath.pyi:{node.lineno}"
        if isinstance(node, ast.FunctionDef):
            api.functions[node.name] = where
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if not (isinstance(node.annotation, ast.Name) and node.annotation.id == "TypeAlias"):
                api.constants[node.target.id] = where
        elif isinstance(node, ast.ClassDef):
            bases = {base.id if isinstance(base, ast.Name) else getattr(base, "attr", "") for base in node.bases}
            if bases & _TYPING_BASES:
                continue
            api.classes[node.name] = where
            members = api.members[node.name] = {}
            settable = api.settable[node.name] = {}
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    decorators = _decorators(item)
                    if "property" in decorators:
                        members[item.name] = "attribute"
                        settable.setdefault(item.name, False)
                    elif "setter" in decorators:
                        settable[item.name] = True
                    elif item.name == "__init__" and len(item.args.args) + len(item.args.kwonlyargs) <= 1:
                        continue  # ``def __init__(self)``: nothing a constructor in C would add
                    else:
                        members[item.name] = "method"
                elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                    members[item.target.id] = "attribute"
                    settable[item.target.id] = True
    return api


# -- comparing --------------------------------------------------------------------------------------


def _names(kind: str, c: dict[str, str], stub: dict[str, str]) -> list[str]:
    return [f"{kind} {name}: in C ({c[name]}), not in the stub" for name in sorted(c.keys() - stub.keys())] + [
        f"{kind} {name}: in the stub ({stub[name]}), not in C" for name in sorted(stub.keys() - c.keys())
    ]


def _a(kind: str) -> str:
    return f"an {kind}" if kind[0] in "aeiou" else f"a {kind}"


def differences(c: Api, stub: Api) -> list[str]:
    """Every name one side has and the other lacks, and every member whose kind differs."""
    found = _names("function", c.functions, stub.functions)
    found += _names("constant", c.constants, stub.constants)
    found += _names("class", c.classes, stub.classes)
    for name in sorted(c.classes.keys() & stub.classes.keys()):
        ours, theirs, where = c.members[name], stub.members[name], c.classes[name]
        for member in sorted(ours.keys() | theirs.keys()):
            if member not in theirs:
                found.append(f"{name}.{member}: {_a(ours[member])} in C ({where}), not in the stub")
            elif member not in ours:
                found.append(f"{name}.{member}: {_a(theirs[member])} in the stub, not in C ({where})")
            elif ours[member] != theirs[member]:
                found.append(f"{name}.{member}: {_a(ours[member])} in C ({where}), {_a(theirs[member])} in the stub")
    return found


def settable_differences(c: Api, stub: Api) -> list[str]:
    """Attributes C lets Python set and the stub does not, or the reverse (a read-only
    attribute is a ``@property`` in a stub; a plain annotation says it can be set)."""
    found = []
    for name in sorted(c.classes.keys() & stub.classes.keys()):
        for member in sorted(c.settable[name].keys() & stub.settable[name].keys()):
            in_c, in_stub = c.settable[name][member], stub.settable[name][member]
            if in_c != in_stub:
                found.append(
                    f"{name}.{member}: {'settable' if in_c else 'read-only'} in C ({c.classes[name]}), "
                    f"{'settable (a plain annotation)' if in_stub else 'read-only (a property)'} in the stub"
                )
    return found


def test_the_parsers_find_what_the_engine_is_made_of() -> None:
    """A parser that finds nothing would let every comparison pass: each side is seen whole."""
    c, stub = c_api(c_sources()), stub_api(STUB.read_text(encoding="utf-8"))
    for api in (c, stub):
        assert {"Notifier", "WaitSet", "Express", "Lock", "KeepLast", "Slots", "Work"} <= api.classes.keys()
        assert {"first_step", "mark_carrier", "poll", "publisher_gid", "stuck_after"} <= api.functions.keys()
        assert {"SUBSCRIPTION", "DRAIN"} <= api.constants.keys()
        assert {"watch", "unwatch", "triggers"} <= api.members["Notifier"].keys()
        assert {"__enter__", "__exit__"} <= api.members["Lock"].keys()
        assert "__len__" in api.members["KeepLast"]
        assert "__init__" in api.members["Handoff"]  # tp_new parses its arguments in C
    assert "Handle" not in stub.classes  # a Protocol: the checkers' description of rclpy's handles
    assert "__init__" not in c.members["Meter"]


#: A small extension in the shape of ``fastpath/``: one type, two tables, a slot, a function, a constant.
_TOY_C = {
    "module.c": """
static PyMethodDef module_methods[] = {
  {"poll", (PyCFunction)poll, METH_O, "poll(x) -> None"},
  {NULL, NULL, 0, NULL},
};
static struct PyModuleDef module = {.m_methods = module_methods};
PyMODINIT_FUNC PyInit__fastpath(void)
{
  static struct { const char * name; PyTypeObject * type; } types[] = {{"Queue", &QueueType}};
  PyModule_AddIntConstant(m, "DEPTH", 4);
}
""",
    "queue.c": """
static PyMethodDef Queue_methods[] = {
  {"push", (PyCFunction)Queue_push, METH_O, "push(item) -> None: {\\"x\\", y}"},
  {"pop", (PyCFunction)Queue_pop, METH_NOARGS, NULL},
  {NULL, NULL, 0, NULL},
};
static PyMemberDef Queue_members[] = {
  {"limit", T_PYSSIZET, offsetof(QueueObject, limit), READONLY, "At most this many."},
  {NULL, 0, 0, 0, NULL},
};
static PySequenceMethods Queue_sequence = {
  .sq_length = (lenfunc)Queue_len,
};
PyTypeObject QueueType = {
  .tp_name = "container.executor._fastpath.Queue",
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Queue_init,
  .tp_methods = Queue_methods,
  .tp_members = Queue_members,
  .tp_as_sequence = &Queue_sequence,
};
""",
}
_TOY_STUB = '''
from typing import Protocol
class Handle(Protocol):
    def close(self) -> None: ...
DEPTH: int
def poll(x: object, /) -> None: ...
class Queue:
    def __init__(self, limit: int) -> None: ...
    def push(self, item: object, /) -> None: ...
    def pop(self) -> object: ...
    @property
    def limit(self) -> int: ...
    def __len__(self) -> int: ...
'''


def test_the_comparison_names_a_difference_either_way() -> None:
    """On a toy extension: equal, then a method only in C, one only in the stub, a function
    the stub lacks, a member that is a method on one side and an attribute on the other."""
    assert differences(c_api(_TOY_C), stub_api(_TOY_STUB)) == []
    assert settable_differences(c_api(_TOY_C), stub_api(_TOY_STUB)) == []
    added = _TOY_C["module.c"].replace('{{"Queue", &QueueType}}', "{}") + "PyModule_AddType(m, &QueueType);\n"
    assert differences(c_api(dict(_TOY_C, **{"module.c": added})), stub_api(_TOY_STUB)) == []
    c_side = dict(_TOY_C, **{"queue.c": _TOY_C["queue.c"].replace('{"pop"', '{"peek"')})
    stub = _TOY_STUB.replace("def poll(", "def wait(").replace("def limit(self)", "def limit(self, n: int)")
    stub = stub.replace("    @property\n", "")
    assert differences(c_api(c_side), stub_api(stub)) == [
        "function poll: in C (module.c (module_methods)), not in the stub",
        "function wait: in the stub (_fastpath.pyi:6), not in C",
        "Queue.limit: an attribute in C (queue.c (QueueType)), a method in the stub",
        "Queue.peek: a method in C (queue.c (QueueType)), not in the stub",
        "Queue.pop: a method in the stub, not in C (queue.c (QueueType))",
    ]
    settable = _TOY_STUB.replace("    @property\n    def limit(self) -> int: ...", "    limit: int")
    assert settable_differences(c_api(_TOY_C), stub_api(settable)) == [
        "Queue.limit: read-only in C (queue.c (QueueType)), settable (a plain annotation) in the stub"
    ]


def test_the_stub_declares_exactly_what_the_c_extension_provides() -> None:
    """``_fastpath.pyi`` against ``PyInit__fastpath``'s types, functions and constants, and
    each type's method, member and getset tables, both ways."""
    found = differences(c_api(c_sources()), stub_api(STUB.read_text(encoding="utf-8")))
    assert not found, "_fastpath.pyi and fastpath/*.c disagree:\n  " + "\n  ".join(found)


def test_the_stub_says_which_attributes_can_be_set() -> None:
    """A member C declares ``READONLY`` (or a getset without a setter) is a ``@property`` in the
    stub, and a settable one a plain annotation: else mypy passes an assignment that raises."""
    found = settable_differences(c_api(c_sources()), stub_api(STUB.read_text(encoding="utf-8")))
    assert not found, "_fastpath.pyi and fastpath/*.c disagree on what can be set:\n  " + "\n  ".join(found)


# -- the module tables ------------------------------------------------------------------------------

_FILE = re.compile(r"`([\w/]+(?:\.pyi?|\.c|/))`")


def executor_files() -> set[str]:
    """The executor's modules as the tables name them: ``_executor.py``, ``_pyengine/held.py``,
    ``fastpath/notifier.c``, ``_fastpath.pyi``; a directory of them as ``fastpath/``, ``_pyengine/``."""
    found: set[str] = set()
    for path in EXECUTOR.rglob("*"):
        relative = path.relative_to(EXECUTOR)
        if "__pycache__" in relative.parts or path.suffix not in (".py", ".pyi", ".c") or not path.is_file():
            continue
        if relative.parent.parts:
            found.add(f"{relative.parent.as_posix()}/")
        if path.name != "__init__.py":
            found.add(relative.as_posix())
    return found


def routes_table() -> set[str]:
    """The files the module table of ``routes.md`` names: a row's own file, and for a
    directory's row (``fastpath/``), the files its job names, in that directory."""
    named: set[str] = set()
    for line in ROUTES.read_text(encoding="utf-8").splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) < 2:
            continue
        row = _FILE.fullmatch(cells[0])
        if row is None:
            continue
        path = row.group(1)
        named.add(path)
        if path.endswith("/"):
            named.update(path + name for name in _FILE.findall(cells[1]) if "/" not in name)
    return named


def test_the_routes_module_table_names_every_module_of_the_executor() -> None:
    table, files = routes_table(), executor_files()
    missing = sorted(files - table)
    assert not missing, f"{ROUTES.relative_to(REPO)}: the module table does not name {', '.join(missing)}"
    pyengine_absent = not (EXECUTOR / PYENGINE / "__init__.py").is_file()
    unknown = sorted(
        name for name in table - files if not (pyengine_absent and name.startswith(PYENGINE))
    )
    assert not unknown, f"{ROUTES.relative_to(REPO)}: the module table names {', '.join(unknown)}, which do not exist"


def contributing_names() -> set[str]:
    """The names the ``executor/`` entry of ``CONTRIBUTING.md``'s layout gives (up to ``intra/``)."""
    text = CONTRIBUTING.read_text(encoding="utf-8")
    start = text.index("  executor/")
    entry = text[start : text.index("  intra/", start)]
    return set(re.findall(r"(?<![\w.])(_\w+/?|fastpath/)", entry))


def test_contributing_names_every_module_of_the_executor() -> None:
    """The layout in ``CONTRIBUTING.md`` names each module by its bare name (``_executor``)."""
    names = contributing_names()
    wanted = {
        name.removesuffix(".py").removesuffix(".pyi")
        for name in executor_files()
        if "/" not in name or (name.endswith("/") and name.count("/") == 1)
    }
    wanted.add("fastpath/")
    missing = sorted(wanted - names)
    assert not missing, f"CONTRIBUTING.md: the layout's executor/ entry does not name {', '.join(missing)}"


@pytest.mark.parametrize(
    "page",
    [*(f"docs/executor/{name}" for name in ("index.md", "routes.md", "contract.md", "waitables.md")), "docs/design.md"],
)
def test_executor_pages_name_only_files_that_exist(page: str) -> None:
    """A path in backticks on the executor's pages (``container/executor/_inbox.py``) is a file of the repository."""
    text = (REPO / page).read_text(encoding="utf-8")
    paths = set(re.findall(r"`((?:container|tests|docs|examples|plugins)/[\w./-]+)`", text))
    pending = f"container/executor/{PYENGINE}"  # being written: see PYENGINE
    gone = sorted(path for path in paths if not (REPO / path).exists() and not path.startswith(pending))
    assert not gone, f"{page} names {', '.join(gone)}, which do not exist"
