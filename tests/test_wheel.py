"""The wheel a user installs: the example sites (so `wsnav demo` works from an install outside the checkout), a
LICENSE and py.typed, no test drivers; and a checkout without symbolic links refuses to build instead of making a
wheel of 10 files that fails at run time."""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from tests.conftest import REPO

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

LEFTOVERS = (".git", ".venv", "build", "out", "*.egg-info", "__pycache__", ".pytest_cache", ".ruff_cache")


def copy_of_checkout(dest: Path) -> Path:
    """A copy to build from: pip builds in the source tree, where another build or a stale file would mix in."""
    shutil.copytree(REPO, dest, symlinks=True, ignore=shutil.ignore_patterns(*LEFTOVERS))
    return dest


def build_wheel(source: Path, out: Path) -> subprocess.CompletedProcess[str]:
    """pip of a fresh venv, as a user's: this environment reaches Debian's ROS packages, whose setuptools would
    take over the build."""
    builder = out.parent / "builder"
    if not builder.exists():
        subprocess.run([sys.executable, "-m", "venv", builder], check=True, timeout=120)
    pip = [builder / "bin" / "python", "-m", "pip", "wheel", "-q", "--no-deps", "--disable-pip-version-check"]
    return subprocess.run([*pip, "-w", out, source], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("wheel")
    built = build_wheel(copy_of_checkout(work / "src"), work / "dist")
    assert built.returncode == 0, built.stderr[-3000:]
    [path] = (work / "dist").glob("wsnav-*.whl")
    return path


def test_the_wheel_carries_the_example_sites_a_license_and_py_typed_and_no_test_drivers(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    for shipped in (
        "wsnav/py.typed",
        "wsnav/sites/school/site.yaml",
        "wsnav/sites/school/map.pgm",
        "wsnav/sites/school/scenarios/raffle.yaml",
        "wsnav/sites/warehouse/site.yaml",
        "wsnav/sites/nav2_maps/warehouse.pgm",
        "wsnav/runtime/bus.py",
        "wsnav/firmware/device/node_logic.py",
        "wsnav/broker/mosquitto/pending_auth.c",  # mosquitto-config --pending-passwords builds it
    ):
        assert shipped in names, shipped
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names), sorted(names)[:20]
    assert not [n for n in names if "host_stubs" in n or n.endswith("generate.py")]
    assert "wsnav/firmware/build.py" in names
    assert not {"wsnav/firmware/testing.py", "wsnav/firmware/unix_board.py"} & names, (
        "the unix port's test drivers"
    )


def test_wsnav_demo_runs_from_an_install_outside_the_checkout(wheel: Path, tmp_path: Path) -> None:
    """It said `sites/school: no such site file`. The wheel goes into a fresh venv; its dependencies are this
    environment's (a .pth line: no second 700 MB install), and the demo runs in an empty folder."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", venv], check=True, timeout=120)
    python = venv / "bin" / "python"
    install = subprocess.run(
        [python, "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check", wheel],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert install.returncode == 0, install.stderr[-2000:]
    site_packages = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(site_packages) / "zz-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    demo = subprocess.run(
        [venv / "bin" / "wsnav", "demo", "--out", "demo"],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        timeout=800,
    )
    assert demo.returncode == 0, demo.stdout[-2000:] + demo.stderr[-2000:]
    assert (elsewhere / "demo" / "demo.png").is_file()
    where = subprocess.run(
        [python, "-I", "-c", "import wsnav; print(wsnav.__file__)"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert where.stdout.startswith(site_packages), where.stdout


def test_a_checkout_without_symlinks_refuses_to_build_in_one_line(tmp_path: Path) -> None:
    """Git for Windows checks symlinks out as text files holding the target (core.symlinks=false)."""
    source = copy_of_checkout(tmp_path / "src")
    for link in (source / "wsnav").iterdir():
        if link.is_symlink():
            target = str(link.readlink())
            link.unlink()
            link.write_text(target)
    built = build_wheel(source, tmp_path / "dist")
    assert built.returncode != 0
    assert "should be symbolic links" in built.stdout + built.stderr, (
        built.stdout[-2000:] + built.stderr[-2000:]
    )
    assert not list((tmp_path / "dist").glob("*.whl")) if (tmp_path / "dist").exists() else True
