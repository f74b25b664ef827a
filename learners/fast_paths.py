"""Fast paths, and the code they copy: one guard for every step on plain tensors.

A fast path computes what a loss module computes, operation for operation, on plain tensors (the
paper's phases in ``learners/monte_carlo/fused.py``; SAC's, TQC's, CrossQ's and TD3's steps in
``losses/``): the same bits, faster. It is a copy of the science, so it runs only while what it
copies is as it was when it was checked against it. What it copies is found from what was built,
not listed by hand:

- every method of the loss's class and of each of its bases, the project's and TorchRL's (an
  edit in a file, a method added in place, one replaced at run time);
- every method of each network class inside the loss (the project's: ``StackedMLP``,
  ``StackedCriticNet``, ...), and of its value estimator's class;
- the functions a fast path names itself (``extra``: the paper's phases copy ``losses.functional``,
  the kernels' backward, the minibatch draw).

Each is compared, as its syntax tree without docstrings (an edit to a docstring or a comment changes
nothing; any edit to what it computes does), with ``learners/fast_paths.json``, written when the fast
paths were last checked bit for bit against the loss modules. If anything differs, or the loss is a
subclass, the loss module computes the run's updates with the edit in effect, the run says so in
one line naming what changed, and ``summary.json``'s ``paths`` records why.

After mirroring an edit in a fast path and passing its tests (``tests/test_fused_phases.py``,
``tests/test_fast_paths.py``), record the code as it now is::

    python -m learners.fast_paths            # what differs from the record, if anything
    python -m learners.fast_paths --record   # write learners/fast_paths.json

Torch-free; the functions take the built loss and import nothing of the project but the file door
(``door.files``, to read the record).
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import inspect
import json
import sys
import textwrap
from pathlib import Path

RECORD = Path(__file__).with_name("fast_paths.json")
# Whose code a fast path may copy: the project's loss and network code and TorchRL's losses. torch's,
# tensordict's and TorchRL's module wrappers are the machinery both paths run alike.
SCOPE = ("losses.", "learners.", "collectors.", "torchrl.objectives.")
MACHINERY = ("torch.", "tensordict.")  # code both paths run alike, never a copy's concern
# The modules whose classes and functions the record holds (everything a fast path can reach).
RECORDED_MODULES = (
    "losses.common", "losses.functional", "losses.ppo", "losses.spg", "losses.td", "losses.sac", "losses.tqc",
    "losses.crossq", "losses.td3",
    "learners.base", "learners.networks", "learners.kernels.ops", "learners.td.learner", "collectors.replay",
    "torchrl.objectives.common", "torchrl.objectives.sac", "torchrl.objectives.tqc", "torchrl.objectives.td3",
    "torchrl.objectives.crossq",
    "torchrl.objectives.value.advantages", "learners.monte_carlo.fused",
)


def _canonical(node) -> str:
    """``node`` as text that does not depend on the Python version (``ast.dump`` leaves out empty fields
    from 3.13 on only) or on positions."""
    if isinstance(node, ast.AST):
        fields = []
        for name, value in ast.iter_fields(node):
            if name == "ctx" or value is None or value == []:
                continue
            fields.append(f"{name}={_canonical(value)}")
        return f"{type(node).__name__}({','.join(fields)})"
    if isinstance(node, list):
        return "[" + ",".join(_canonical(item) for item in node) + "]"
    return repr(node)


def _without_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and body \
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                and isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]
    return tree


def source_digest(source: str) -> str:
    """The digest of one definition's source: the SHA-256 (16 hex digits) of its syntax tree without
    docstrings, in a form that does not depend on the Python version."""
    tree = ast.parse(source)
    if len(tree.body) != 1 or not isinstance(tree.body[0], (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        raise ValueError("not one definition")
    return hashlib.sha256(_canonical(_without_docstrings(tree)).encode()).hexdigest()[:16]


_DIGESTS: dict = {}  # function object -> digest (a function replaced at run time is another object)


def function_digest(function) -> str | None:
    """The first 16 hex digits of the SHA-256 of ``function``'s code (its syntax tree without
    docstrings), or None where its source cannot be read (a lambda on a line with other code, a
    function made at run time)."""
    try:
        return _DIGESTS[function]
    except (KeyError, TypeError):
        pass
    code = getattr(function, "__code__", None)
    if code is not None and code.co_filename.startswith("<"):  # made at run time from a template (a dataclass's
        return f"<generated {function.__name__}>"                  # __init__): its class's own code says what it is
    try:
        digest = source_digest(textwrap.dedent(inspect.getsource(function)))
    except (OSError, TypeError, SyntaxError, ValueError, IndentationError):
        digest = f"<class {function.__name__}>" if inspect.isclass(function) else None  # a class made by a metaclass
    try:
        _DIGESTS[function] = digest
    except TypeError:
        pass
    return digest


def _code_of(value):
    """The function (or class) behind a class member, or None for data: a class's data is state (TorchRL
    and tensordict set some of it on the class when a first instance is built), its code is what runs."""
    if isinstance(value, (staticmethod, classmethod)):
        value = value.__func__
    if isinstance(value, property):
        value = value.fget
    return value if inspect.isfunction(value) or inspect.isclass(value) else None


def _member_digest(value) -> str | None:
    """A class member's digest: its function's (methods, static and class methods), its getter's, setter's
    and deleter's for a property."""
    if isinstance(value, property):
        parts = [function_digest(f) for f in (value.fget, value.fset, value.fdel) if f is not None]
        return None if None in parts else hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]
    return function_digest(_code_of(value))


def in_scope(obj) -> bool:
    return f"{getattr(obj, '__module__', '')}.".startswith(SCOPE)


def class_digests(cls: type) -> dict[str, str | None]:
    """{module.Class.member: digest} for every member ``cls`` and its bases within ``SCOPE`` define."""
    found = {}
    for klass in cls.__mro__:
        if not in_scope(klass):
            continue
        for name, value in vars(klass).items():
            code = _code_of(value)
            # any code but the machinery's (tensordict's metaclass adds properties to TorchRL's losses)
            if code is not None and not f"{code.__module__}.".startswith(MACHINERY):
                found[f"{klass.__module__}.{klass.__qualname__}.{name}"] = _member_digest(value)
    return found


def copied_units(loss, extra=()) -> list:
    """The classes and functions a fast path computing ``loss``'s steps copies: the loss's class, the
    classes of the networks inside it (within ``SCOPE``), its value estimator's class, and ``extra``."""
    units = [type(loss)]
    # TorchRL keeps a loss's networks outside its registered submodules (in its __dict__): both are walked
    holders = [loss, *(value for value in vars(loss).values() if hasattr(value, "named_modules"))]
    for holder in holders:
        for module in holder.modules():
            if module is not loss and in_scope(type(module)) and type(module) not in units:
                units.append(type(module))
    estimator = getattr(loss, "_value_estimator", None)
    if estimator is not None and type(estimator) not in units:
        units.append(type(estimator))
    return units + [unit for unit in extra if unit not in units]


def digests(units) -> dict[str, str | None]:
    """{qualified name: digest} of ``units`` (classes expand to their members, bases included)."""
    found = {}
    for unit in units:
        if inspect.isclass(unit):
            found.update(class_digests(unit))
        else:
            found[f"{unit.__module__}.{unit.__qualname__}"] = function_digest(unit)
    return found


def _recorded() -> dict[str, str]:
    from door import files  # the one door (stdlib only)

    return json.loads(files.read_text(RECORD, 2_000_000, "fast-path record"))["digests"]


_RECORD: dict | None = None


def recorded() -> dict[str, str]:
    """The record (``learners/fast_paths.json``), read once per process."""
    global _RECORD
    if _RECORD is None:
        _RECORD = _recorded()
    return _RECORD


def changed(loss, extra=()) -> list[str]:
    """What a fast path for ``loss`` copies that is not as recorded: edited, added or unreadable."""
    record = recorded()
    return [name for name, digest in digests(copied_units(loss, extra)).items()
            if digest is None or record.get(name) != digest]


def refusal(loss, extra=()) -> str | None:
    """Why a fast path may not compute ``loss``'s steps because of code (None: it may): ``loss``'s class
    is code outside ``SCOPE`` (a researcher's subclass in a script), or code it copies changed
    (``changed``: a subclass in the project's files is new code, named by its methods)."""
    outside = []
    for klass in type(loss).__mro__:
        if in_scope(klass):
            break
        outside.append(klass)
    if outside:
        return (f"the loss is a {outside[0].__module__}.{outside[0].__qualname__}, code the fast path was not "
                "checked against")
    edited = changed(loss, extra)
    if not edited:
        return None
    more = f" and {len(edited) - 3} more" if len(edited) > 3 else ""
    return (f"{', '.join(edited[:3])}{more} changed since the fast path was checked against "
            f"{'it' if len(edited) == 1 else 'them'} (learners/fast_paths.json)")


def own_edits(prefixes) -> list[str]:
    """The fast paths' own code (recorded functions and class members whose qualified names start with one of
    ``prefixes``: ``losses.td3.fused_``, ``learners.monte_carlo.fused.``) that is not as recorded: an edit a run
    whose updates are the loss module's (``compile=true``, a setting the fast path does not compute) does not run,
    and says so (``engine.run_context``)."""
    prefixes = tuple(prefixes)
    if not prefixes:
        return []
    record = recorded()
    now = {}
    for name in {key.rsplit(".", 1)[0] for key in record if key.startswith(prefixes)} | {
            p.rstrip("._") for p in prefixes}:
        module = name
        while module and module not in RECORDED_MODULES:
            module = module.rpartition(".")[0]
        if module:
            now.update({key: digest for key, digest in _module_digests(module).items() if key.startswith(prefixes)})
    names = sorted(set(now) | {key for key in record if key.startswith(prefixes)})
    return [name for name in names if now.get(name) is None or record.get(name) != now.get(name)]


def _module_digests(name: str) -> dict[str, str | None]:
    module = importlib.import_module(name)
    found = {}
    for value in vars(module).values():
        if getattr(value, "__module__", None) != name:
            continue
        if inspect.isclass(value):
            found.update({key: digest for key, digest in class_digests(value).items()
                          if key.startswith(f"{name}.{value.__qualname__}.")})
        elif inspect.isfunction(value):
            found[f"{name}.{value.__qualname__}"] = function_digest(value)
    return found


def record_now() -> dict[str, str]:
    """Every class member and function of ``RECORDED_MODULES`` as its code is now."""
    found = {}
    for name in RECORDED_MODULES:
        found.update(_module_digests(name))
    return dict(sorted(found.items()))


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m learners.fast_paths", description=__doc__.split("\n\n")[0])
    parser.add_argument("--record", action="store_true", help="write learners/fast_paths.json from the code as it is")
    args = parser.parse_args(argv)
    import torchrl

    now = record_now()
    if args.record:
        from door import files

        text = json.dumps({"torchrl": torchrl.__version__, "digests": now}, indent=1) + "\n"
        files.write_text(RECORD, text)
        print(f"recorded {len(now)} functions in {RECORD.name}")
        return 0
    record = recorded()
    differ = sorted(name for name in set(now) | set(record) if now.get(name) != record.get(name))
    for name in differ:
        print(f"{name}: recorded {record.get(name)}, now {now.get(name)}")
    print(f"{len(differ)} of {len(now)} differ from {RECORD.name}" if differ else f"all {len(now)} as recorded")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool  # a command's entry point is the top of the house

    sys.exit(run_tool("learners.fast_paths", main))
