"""The extension's type stubs (ctxrace/_ctxrace.pyi) name what the extension holds: every
public name, and each function's and method's parameters in order, as the compiled module's
own signatures give them."""

import ast
import inspect
from pathlib import Path

from ctxrace import _ctxrace

STUB = Path(__file__).resolve().parents[1] / "python" / "ctxrace" / "_ctxrace.pyi"


def stub_tree():
    """The stub's module-level names: constants, functions' parameters, classes' members."""
    names, functions, classes = set(), {}, {}
    for node in ast.parse(STUB.read_text()).body:
        if isinstance(node, ast.AnnAssign):
            names.add(node.target.id)
        elif isinstance(node, ast.FunctionDef):
            functions[node.name] = [a.arg for a in node.args.args]
        elif isinstance(node, ast.ClassDef):
            members = {}
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    members[item.name] = [a.arg for a in item.args.args if a.arg != "self"]
            classes[node.name] = members
    return names | set(functions) | set(classes), functions, classes


def parameters(obj):
    """The parameter names of a compiled function or method, `self` left out."""
    return [p for p in inspect.signature(obj).parameters if p != "self"]


def test_the_stubs_name_what_the_extension_holds():
    names, functions, classes = stub_tree()
    public = {n for n in dir(_ctxrace) if not n.startswith("_")} | {"__version__"}
    assert names == public
    for name, params in functions.items():
        assert params == parameters(getattr(_ctxrace, name)), name
    for name, members in classes.items():
        cls = getattr(_ctxrace, name)
        compiled = {m for m in vars(cls) if not m.startswith("_")}
        assert set(members) - {"__init__"} == compiled, name
        assert members["__init__"] == parameters(cls), name
        for member, params in members.items():
            attr = inspect.getattr_static(cls, member)
            if member != "__init__" and callable(attr):
                assert params == parameters(getattr(cls, member)), f"{name}.{member}"
