"""Every import of the package is declared in pyproject.toml, in the extra of the module that makes it.

`pip install dmlo` gives the core dependencies; each extra (`train`, `plot`, `io`, `argoverse2`, `bench`) adds
what its modules import. The static check parses every module under `python/dmlo` and holds each import,
at module level or inside a function, to the extras its module belongs to (`EXTRAS_OF` below); an import
inside `try: ... except ImportError` is an optional one, whose fallback says what to install, and only
has to be declared somewhere. Then the core is imported for real with every other extra's packages made
unimportable, as on a machine with `pip install dmlo` alone.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from support import REPO

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

PACKAGE = REPO / "python" / "dmlo"

# Which extras a module needs beyond the core, by the longest matching module-name prefix; anything not
# listed is core. A module listed here may import what these extras declare; a core module may import
# another module's extra only lazily (inside a function) or guarded by `except ImportError`.
EXTRAS_OF: dict[str, tuple[str, ...]] = {
    "dmlo.model": ("train",),
    "dmlo.train": ("train",),
    "dmlo.export": ("train",),
    "dmlo.commands.train": ("train",),
    "dmlo.commands.export": ("train",),
    "dmlo.plot": ("plot",),
    "dmlo.peers": ("bench",),
}

# Distributions whose import name is not their normalised project name.
IMPORT_NAMES = {"python-neo-lzf": "lzf"}

# Built with the package itself (maturin builds dmlo_rs into the same wheel).
FIRST_PARTY = {"dmlo", "dmlo_rs"}


def _import_name(requirement: str) -> str:
    project = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", requirement)
    assert project is not None, requirement
    name = project.group(0).lower()
    return IMPORT_NAMES.get(name, name.replace("-", "_").replace(".", "_"))


def declared() -> tuple[set[str], dict[str, set[str]]]:
    """The import names of the core dependencies, and of each extra (its own requirements only; an extra
    naming `dmlo[...]` gets those extras' too)."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    extras_table: dict[str, list[str]] = project["optional-dependencies"]

    def resolve(extra: str) -> set[str]:
        names: set[str] = set()
        for requirement in extras_table[extra]:
            nested = re.fullmatch(r"dmlo\[([^\]]+)\]", requirement.replace(" ", ""))
            if nested:
                for inner in nested.group(1).split(","):
                    names |= resolve(inner)
            else:
                names.add(_import_name(requirement))
        return names

    core = {_import_name(r) for r in project["dependencies"]}
    return core, {extra: resolve(extra) for extra in extras_table}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def extras_of(module: str) -> tuple[str, ...]:
    matches = [prefix for prefix in EXTRAS_OF if module == prefix or module.startswith(prefix + ".")]
    return EXTRAS_OF[max(matches, key=len)] if matches else ()


@dataclass
class Imports:
    """A module's imports, by top-level name, with the line of each."""

    required: dict[str, int] = field(default_factory=dict)  # run whenever the code containing them runs
    optional: dict[str, int] = field(default_factory=dict)  # inside try/except ImportError
    first_party_at_import: dict[str, int] = field(default_factory=dict)  # dmlo.* modules imported at module level


def _guards_import_error(handler: ast.ExceptHandler) -> bool:
    if handler.type is None:
        return True
    names = [handler.type] if not isinstance(handler.type, ast.Tuple) else list(handler.type.elts)
    return any(isinstance(n, ast.Name) and n.id in ("ImportError", "ModuleNotFoundError", "Exception") for n in names)


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def collect_imports(path: Path) -> Imports:
    imports = Imports()

    def record(node: ast.Import | ast.ImportFrom, in_function: bool, guarded: bool) -> None:
        if isinstance(node, ast.ImportFrom):
            if node.level or node.module is None:
                return  # relative: first party
            names = [node.module]
        else:
            names = [alias.name for alias in node.names]
        for name in names:
            top = name.split(".")[0]
            if top in sys.stdlib_module_names or top == "__future__":
                continue
            if top == "dmlo":
                if not in_function and not guarded:
                    imports.first_party_at_import.setdefault(name, node.lineno)
                continue
            if top in FIRST_PARTY:
                continue
            (imports.optional if guarded else imports.required).setdefault(top, node.lineno)

    def visit(body: list[ast.stmt], in_function: bool, guarded: bool) -> None:
        for node in body:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                record(node, in_function, guarded)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(node.body, True, guarded)
            elif isinstance(node, ast.ClassDef):
                visit(node.body, in_function, guarded)
            elif isinstance(node, ast.If) and _is_type_checking(node):
                continue  # never runs
            elif isinstance(node, ast.Try):
                visit(node.body, in_function, guarded or any(_guards_import_error(h) for h in node.handlers))
                for handler in node.handlers:
                    visit(handler.body, in_function, guarded)
                visit(node.orelse, in_function, guarded)
                visit(node.finalbody, in_function, guarded)
            else:  # if, for, while, with, match: the statements inside run with the same guard
                for child in ast.iter_child_nodes(node):
                    if isinstance(child, ast.stmt):
                        visit([child], in_function, guarded)
                    elif isinstance(child, ast.match_case):
                        visit(child.body, in_function, guarded)

    visit(ast.parse(path.read_text(), str(path)).body, False, False)
    return imports


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_the_module_table_and_the_extras_agree() -> None:
    _, extras = declared()
    assert {"train", "plot", "io", "argoverse2", "bench"} <= set(extras)
    for prefix, needed in EXTRAS_OF.items():
        assert set(needed) <= set(extras), f"{prefix}: unknown extra(s) {set(needed) - set(extras)}"
    # The test extra installs every extra whose modules the tests import (.ci/setup installs `test`).
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    nested = next(r for r in project["optional-dependencies"]["test"] if r.startswith("dmlo["))
    assert {"train", "plot", "io", "argoverse2"} <= set(nested[5:-1].split(","))


def test_collect_imports_sees_every_kind_of_import(tmp_path: Path) -> None:
    source = tmp_path / "sample.py"
    source.write_text(
        "from __future__ import annotations\nimport os\nimport numpy as np\nfrom typing import TYPE_CHECKING\n"
        "from dmlo.poses import as_poses\nif TYPE_CHECKING:\n    import torch\n"
        "try:\n    import lzf\nexcept ImportError:\n    lzf = None\n"
        "def f():\n    import scipy.spatial\n    from dmlo.plot import plot_trajectories\n"
        "    try:\n        import pyarrow.feather as feather\n    except (ImportError, OSError):\n        pass\n"
        "class C:\n    def g(self):\n        if True:\n            from matplotlib.figure import Figure\n"
        "with open('x') as handle:\n    import tqdm\n"
    )
    found = collect_imports(source)
    assert found.required == {"numpy": 3, "scipy": 13, "matplotlib": 22, "tqdm": 24}
    assert found.optional == {"lzf": 9, "pyarrow": 16}
    assert found.first_party_at_import == {"dmlo.poses": 5}


@pytest.mark.parametrize("path", MODULES, ids=lambda p: module_name(p))
def test_each_module_imports_only_what_its_extras_declare(path: Path) -> None:
    core, extras = declared()
    module = module_name(path)
    needed = extras_of(module)
    allowed = core.union(*(extras[e] for e in needed))
    everything = core.union(*(names for name, names in extras.items() if name != "test"))
    found = collect_imports(path)
    undeclared = {name: line for name, line in found.required.items() if name not in allowed}
    where = f"{module} ({'core' if not needed else 'core + ' + ', '.join(needed)})"
    assert not undeclared, (
        f"{where} imports {undeclared} (name: line) that its extras do not declare in pyproject.toml; "
        "declare it, move the module to an extra (EXTRAS_OF), or guard the import with except ImportError"
    )
    unknown = {name: line for name, line in found.optional.items() if name not in everything}
    assert not unknown, f"{where}: optional import(s) {unknown} are in no extra, so no one can install them"
    # What a module imports at import time needs no extra beyond the module's own.
    for target, line in found.first_party_at_import.items():
        beyond = set(extras_of(target)) - set(needed)
        assert not beyond, f"{where} imports {target} at line {line}, which needs the extra(s) {beyond}"


def test_the_core_imports_with_no_extra_installed() -> None:
    # Every core module, and the command line with all its subcommands, on a machine with `pip install dmlo`:
    # the packages of every extra are made unimportable first.
    core, extras = declared()
    blocked = set().union(*(names for name, names in extras.items() if name != "test")) - core
    modules = [module_name(p) for p in MODULES if not extras_of(module_name(p)) and p.name != "__main__.py"]
    script = f"""
import importlib, importlib.abc, sys
BLOCKED = {sorted(blocked)!r}

class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked: not a core dependency)", name=name)
        return None

sys.meta_path.insert(0, Blocker())
for module in {modules!r}:
    importlib.import_module(module)
from dmlo.cli import build_parser
build_parser()
leaked = sorted(name for name in sys.modules if name.split(".")[0] in BLOCKED)
assert not leaked, leaked
print("ok", len({modules!r}))
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("ok ")
    assert {"lzf", "matplotlib", "scipy", "torch"} <= blocked


def test_the_command_line_names_the_extra_of_a_missing_package(tmp_path: Path) -> None:
    from dmlo.cli import EXTRA_OF_PACKAGE

    _, extras = declared()
    for package, extra in EXTRA_OF_PACKAGE.items():
        assert package in extras[extra], f"{package} is not in the {extra} extra of pyproject.toml"
    # `dmlo train` without PyTorch: one line saying what to install, no traceback, nothing written.
    (tmp_path / "data").mkdir()
    code = (
        "import sys; sys.modules['torch'] = None; from dmlo.cli import main; "
        f"sys.exit(main(['train', '--data', {str(tmp_path / 'data')!r}, '--out', {str(tmp_path / 'run')!r}]))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 1
    assert result.stderr.strip() == "dmlo train: error: torch is not installed: pip install 'dmlo[train]'"
    assert not (tmp_path / "run").exists()
