"""The numerical core stays pure: analytics imports no service, connector, I/O,
web, database or plotting library (DESIGN.md, "Packages")."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = (
    "service",
    "connectors",
    "fastapi",
    "starlette",
    "uvicorn",
    "sqlalchemy",
    "alembic",
    "asyncua",
    "pymodbus",
    "httpx",
    "requests",
    "yaml",
    "matplotlib",
    "plotly",
    "bokeh",
    "seaborn",
    "pandas",
    "resvg_py",
    "playwright",
    "socket",
    "sqlite3",
    "asyncio",
)
# numpy and numba use the standard library's socket and asyncio internally, so
# only the third-party stack and our own packages are poisoned at run time.
POISONED = tuple(name for name in FORBIDDEN if name not in ("socket", "sqlite3", "asyncio"))
ANALYTICS_MODULES = sorted(ROOT.glob("analytics/**/*.py"))


def imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


@pytest.mark.parametrize("path", ANALYTICS_MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_analytics_module_imports_nothing_forbidden(path):
    assert not imported_roots(path) & set(FORBIDDEN)


def test_analytics_imports_with_the_service_stack_missing():
    # Poison the forbidden packages, then import every analytics module.
    modules = [".".join(p.relative_to(ROOT).with_suffix("").parts) for p in ANALYTICS_MODULES]
    code = (
        "import sys\n"
        f"for name in {POISONED!r}: sys.modules[name] = None\n"
        f"for module in {modules!r}: __import__(module)\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)


def test_the_scan_catches_a_forbidden_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from service.api import app\nimport numpy as np\n")
    assert imported_roots(bad) & set(FORBIDDEN) == {"service"}


def test_every_router_has_its_mirrored_route_tests():
    """``service/api/routes/<route>.py`` is tested in ``tests/service/api/test_<route>.py``."""
    routes = {p.stem for p in (ROOT / "service/api/routes").glob("*.py") if p.stem != "__init__"}
    tested = {p.stem.removeprefix("test_") for p in (ROOT / "tests/service/api").glob("test_*.py")}
    assert sorted(routes - tested) == []
