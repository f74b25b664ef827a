"""One door for every file: no module of the project but door/files.py opens, writes, replaces,
renames or deletes a file itself (docs/guarantees.md, "One door").

The check reads every Python file of the project (tests aside) and refuses any call that touches
the file system by name: ``open``, ``os.open``, ``Path.open``/``read_text``/``write_bytes``/...,
``unlink``, ``rename``, ``replace`` (Path's, one argument), ``mkdir``, ``shutil``'s copies and
removals, ``tempfile``'s files, ``zipfile``/``tarfile``/``torch``/``numpy`` given a path, figure
and image writers given a path, ``rglob`` (which follows links). In-memory buffers (``io.BytesIO``,
imageio's ``"<bytes>"``) are fine: their bytes then go through the door.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOOR = ROOT / "door" / "files.py"
SKIP_PARTS = {".venv", "tests", "outputs", "build", ".git", "__pycache__"}

# attribute calls that touch a file by name, on any receiver (Path methods, os functions)
BY_NAME = {"read_text", "read_bytes", "write_text", "write_bytes", "unlink", "rmdir", "rmtree", "rename",
           "mkdir", "makedirs", "touch", "symlink_to", "hardlink_to", "link_to", "savefig", "mimsave", "mimwrite",
           "fdopen", "mkstemp", "mkdtemp", "extractall", "rglob", "imwrite", "chmod", "truncate", "removedirs", "copyfile",
           "copytree", "copy2", "move", "symlink", "mknod", "mkfifo"}
OS_FUNCTIONS = {"open", "remove", "replace", "link", "unlink", "rename", "renames", "mkdir", "makedirs", "rmdir"}
SHUTIL_ALLOWED = {"which", "disk_usage", "get_terminal_size"}
BUFFER_CALLS = {"BytesIO", "StringIO"}


def _buffer(node: ast.AST, buffers: set[str]) -> bool:
    """Whether ``node`` is an in-memory buffer: ``io.BytesIO(...)``, a name bound to one, or "<bytes>"."""
    if isinstance(node, ast.Call):
        func = node.func
        return (isinstance(func, ast.Attribute) and func.attr in BUFFER_CALLS) or (
            isinstance(func, ast.Name) and func.id in BUFFER_CALLS)
    if isinstance(node, ast.Name):
        return node.id in buffers
    return isinstance(node, ast.Constant) and node.value == "<bytes>"


def _buffers(tree: ast.AST) -> set[str]:
    """Names a module binds to an in-memory buffer (``x = io.BytesIO()``, or a parameter typed so)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and _buffer(node.value, set()):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        if isinstance(node, ast.arg) and node.annotation is not None and "BytesIO" in ast.unparse(node.annotation):
            names.add(node.arg)
    return names


def violations(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    buffers = _buffers(tree)
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func, args = node.func, node.args
        receiver = func.value.id if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) else None
        what = None
        if receiver in ("files", "door"):  # the door's own functions (door.files, imported as files or door)
            continue
        if isinstance(func, ast.Name) and func.id in ("open", "ZipFile", "TarFile"):
            if not (func.id == "ZipFile" and args and _buffer(args[0], buffers)):
                what = func.id
        elif isinstance(func, ast.Attribute):
            name = func.attr
            if receiver == "os" and name in OS_FUNCTIONS:
                what = f"os.{name}"
            elif receiver == "shutil" and name not in SHUTIL_ALLOWED:
                what = f"shutil.{name}"
            elif name in ("savefig", "imwrite", "mimwrite") and args and _buffer(args[0], buffers):
                pass
            elif name == "save" and isinstance(func.value, ast.Attribute) and func.value.attr == "image":
                if not (len(args) > 1 and _buffer(args[1], buffers)):  # pygame.image.save(surface, path)
                    what = "image.save"
            elif name in BY_NAME:
                what = name
            elif name == "replace" and len(args) == 1 and not node.keywords:  # Path.replace(target), not str's
                what = "replace"
            elif name == "open":  # Path.open, io.open, tarfile.open(name), gzip.open, ...
                if not (receiver == "tarfile" and any(k.arg == "fileobj" for k in node.keywords)):
                    what = f"{receiver or '...'}.open"
            elif name == "ZipFile" and not (args and _buffer(args[0], buffers)):
                what = "zipfile.ZipFile"
            elif receiver in ("torch", "np", "numpy") and name in ("save", "load", "savez", "savetxt", "loadtxt"):
                target = (args[1] if name == "save" and receiver == "torch" else args[0]) if args else None
                if target is None or not _buffer(target, buffers):
                    what = f"{receiver}.{name}"
        if what is not None:
            found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {what}")
    return found


def project_files() -> list[Path]:
    return sorted(p for p in ROOT.rglob("*.py") if not SKIP_PARTS & set(p.relative_to(ROOT).parts) and p != DOOR)


def test_no_module_but_the_door_touches_a_file_by_name():
    found = [line for path in project_files() for line in violations(path)]
    assert not found, ("these calls touch files outside door/files.py (the one door; docs/guarantees.md): "
                       "read, write, replace or delete through it instead:\n" + "\n".join(found))


def test_the_check_finds_each_kind_of_call(tmp_path):
    """The check itself: each form it must find is found, and buffers are left alone."""
    sample = ROOT / "tests" / "_one_door_sample.py"  # inside ROOT for relative_to; removed after
    calls = ["open('x')", "os.open('x', 0)", "Path('x').read_text()", "p.write_bytes(b'')", "p.unlink()",
             "os.replace('a', 'b')", "p.replace(q)", "shutil.rmtree('x')", "shutil.copy('a', 'b')",
             "p.mkdir()", "torch.save(obj, 'x.pt')", "torch.load('x.pt')", "np.load('x.npy')",
             "zipfile.ZipFile('x.zip')", "tarfile.open('x.tar')", "fig.savefig('x.png')", "imageio.imwrite('x.png', f)",
             "tempfile.mkstemp()", "p.rglob('*')", "tar.extractall('x')", "os.remove('x')", "p.open()",
             "pg.image.save(surface, 'x.png')"]
    fine = ["'a'.replace('b', 'c')", "torch.save(obj, io.BytesIO())", "zipfile.ZipFile(io.BytesIO(b''))",
            "tarfile.open(fileobj=io.BytesIO(b''))", "imageio.imwrite('<bytes>', f, extension='.gif')",
            "buffer = io.BytesIO()\ntorch.save(obj, buffer)", "shutil.which('g++')", "items.remove(3)",
            "fig.savefig(io.BytesIO(), format='png')", "files.write_text(p, 'x')", "files.remove(p)",
            "pg.image.save(surface, io.BytesIO(), 'x.png')"]
    try:
        sample.write_text("\n".join(calls) + "\n")
        assert len(violations(sample)) == len(calls), violations(sample)
        sample.write_text("\n".join(fine) + "\n")
        assert violations(sample) == []
    finally:
        sample.unlink(missing_ok=True)


def test_every_command_line_tool_ends_through_run_tool():
    """Every tool's refusals end in one line (``engine.processes.run_tool`` turns the file door's
    ``FileRefused`` into one, and a signal into one): a module run as a command hands its ``main`` to
    it. train.py has Hydra's own path (``engine.command.run``), tested in tests/test_train.py."""
    missing = []
    for path in project_files():
        text = path.read_text()
        if 'if __name__ == "__main__":' in text and path.name != "train.py":
            block = text[text.index('if __name__ == "__main__":'):]
            if "run_tool(" not in block:
                missing.append(str(path.relative_to(ROOT)))
    assert not missing, f"these commands do not end through engine.processes.run_tool: {missing}"
