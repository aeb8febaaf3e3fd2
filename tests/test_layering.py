"""Imports point one way (STYLE.md): cadreg -> nothing of ours; service -> cadreg; clients -> service wire only."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

FORBIDDEN = {
    "cadreg": {"fastapi", "zenoh", "httpx", "uvicorn", "starlette", "service", "clients", "prometheus_client"},
    "service": {"clients"},
    "clients": set(),
}
# clients may use only the service's wire schemas, codec, error table and zenoh wire contract (keys, encodings)
CLIENTS_MAY_IMPORT_FROM_SERVICE = {"service.schemas", "service.codec", "service.errors", "service.zenoh_wire"}


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module in ("service", "clients", "cadreg"):
                # `from service import codec` imports the module service.codec
                names += [f"{node.module}.{a.name}" for a in node.names]
            else:
                names.append(node.module)
    return names


def test_imports_point_one_way() -> None:
    bad = []
    for package, forbidden in FORBIDDEN.items():
        for path in (REPO / package).rglob("*.py"):
            for name in _imports(path):
                top = name.split(".")[0]
                if top in forbidden:
                    bad.append(f"{path.relative_to(REPO)} imports {name}")
                if package == "clients" and top == "service" and name not in CLIENTS_MAY_IMPORT_FROM_SERVICE:
                    bad.append(f"{path.relative_to(REPO)} imports {name} (clients use only the wire modules)")
    assert not bad, "\n".join(bad)


def test_core_has_no_print_or_environment() -> None:
    bad = []
    for path in (REPO / "cadreg").rglob("*.py"):
        if "cli" in path.relative_to(REPO / "cadreg").parts:
            continue  # the CLI is a runner: it owns output
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                bad.append(f"{path.relative_to(REPO)}:{node.lineno} print()")
            if isinstance(node, ast.Attribute) and node.attr == "environ":
                bad.append(f"{path.relative_to(REPO)}:{node.lineno} os.environ")
    assert not bad, "\n".join(bad)


def test_building_the_cli_parser_and_a_servers_parent_import_no_localizer() -> None:
    """Every command builds the whole parser, `cadreg serve` too, whose workers (not its parent) localize: the
    parser's choices come from light modules, and the parent's modules import neither the localizer, its compiled
    loops, the registration libraries nor SciPy's spatial module (`geometry` imports it on first use). They cost a
    server's parent about a second before it starts its workers."""
    heavy = ("numba", "open3d", "small_gicp", "scipy.spatial", "cadreg.localize.localizer", "cadreg.bench")
    for setup in ("from cadreg.cli.main import build_parser; build_parser()",
                  "import service.runtime, service.http_app, service.settings"):
        code = f"import sys; {setup}; print(','.join(m for m in {heavy!r} if m in sys.modules))"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
        assert out.stdout.strip() == "", setup
