"""Data flows one way (suite -> policy -> method -> harness): no package imports one downstream
of it, except the methods' one arrow up to the data contract `harness.datasets`."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ORDER = ("suites", "policies", "methods", "harness")  # upstream first
ALLOWED_UP = {("methods", "harness.datasets")}


def imported_modules(path: Path) -> list[str]:
    names = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def upward_imports(root: Path = ROOT) -> list[str]:
    found = []
    for package in ORDER:
        for path in sorted((root / package).rglob("*.py")):
            for module in imported_modules(path):
                target = module.split(".")[0]
                if target not in ORDER or ORDER.index(target) <= ORDER.index(package):
                    continue
                if (package, module) not in ALLOWED_UP:
                    found.append(f"{path.relative_to(root)} imports {module}")
    return found


def test_no_module_imports_one_downstream_of_it():
    assert upward_imports() == []


def test_the_check_sees_an_upward_import(tmp_path):
    fake = tmp_path / "suites"
    fake.mkdir()
    (fake / "bad.py").write_text("def f():\n    from harness.errors import RetainError\n")
    (fake / "fine.py").write_text("from suites.base import SuiteError\n")
    for package in ORDER[1:]:
        (tmp_path / package).mkdir()
    assert upward_imports(tmp_path) == ["suites/bad.py imports harness.errors"]
