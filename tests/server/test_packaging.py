"""The wheel holds the product only: pipeline and server, with the Alembic scripts as data of the service."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_wheel_ships_migrations_inside_the_service_and_no_bench_tests_or_seeds(tmp_path: Path) -> None:
    # A clean copy of what the Dockerfile copies: a build/ directory left in the checkout must not leak in.
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    for name in ("pipeline", "server", "migrations"):
        shutil.copytree(REPO / name, src / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(tmp_path)],
                   check=True, capture_output=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("gaitmon-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"pipeline", "server"}
    versions = sorted(p.name for p in (REPO / "migrations" / "versions").glob("*.py"))
    assert versions and [n.rsplit("/", 1)[1] for n in sorted(names) if n.startswith(
        "server/migrations/versions/")] == versions
    assert {"server/migrations/env.py", "server/migrations/script.py.mako", "server/migrate.py"} <= set(names)
    assert not any("seed" in n or n.startswith(("bench/", "tests/", "migrations/")) for n in names)
