"""Data flows one way: import-linter's contracts in pyproject.toml (`make lint`) hold on the tree,
and each kind of wrong import added to a copy of it breaks the contract that forbids it."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("harness", "methods", "policies", "suites")
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"


def lint_imports(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", "--no-logo"], cwd=root,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=120)


def copy_of_the_tree(dest: Path) -> Path:
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            target = dest / path.relative_to(ROOT)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, target)
    shutil.copyfile(ROOT / "pyproject.toml", dest / "pyproject.toml")
    return dest


def test_the_tree_keeps_every_contract():
    proc = lint_imports(ROOT)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "5 kept, 0 broken" in proc.stdout


@pytest.mark.parametrize("module, added, contract, chain", [
    # the data layer reaching up to the commands
    ("harness/data/datasets.py", "from harness.run.cli import main",
     "one-way data flow", "harness.data.datasets -> harness.run.cli"),
    # a simulator suite importing the harness, even inside a function
    ("suites/base.py", "def f():\n    from harness.common.errors import RetainError",
     "suites are simulators and experts only", "suites.base -> harness.common.errors"),
    # a policy importing a method
    ("policies/base.py", "import methods.consft",
     "policies are models only", "policies.base -> methods.consft"),
    # a method reaching past the data contract
    ("methods/er.py", "from harness.data.prepare import prepare_data",
     "methods read the harness only through the data contract", "methods.er -> harness.data.prepare"),
    # two modules of one package importing each other
    ("harness/run/plan.py", "import harness.run.study",
     "no import cycles", ".plan -> .study"),
])
def test_an_added_wrong_import_breaks_its_contract(tmp_path, module, added, contract, chain):
    tree = copy_of_the_tree(tmp_path)
    path = tree / module
    path.write_text(path.read_text() + "\n\n" + added + "\n")
    proc = lint_imports(tree)
    out = " ".join(proc.stdout.split())  # the report wraps long names
    assert proc.returncode == 1, out[-3000:]
    broken = out.split("Broken contracts")[1]  # an import may break more than one contract
    assert contract in broken and chain in broken
