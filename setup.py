"""Refuses to build from a checkout without symbolic links: wsnav/<component> link to the top-level folders, and a
checkout that made them one-line text files (Git for Windows' default, core.symlinks=false) built a wheel of 10
files that said nothing and failed at run time (`ModuleNotFoundError: wsnav.runtime`). Leaves the firmware's test
drivers out of the wheel (TEST_DRIVERS). Everything else is in pyproject.toml."""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

TEST_DRIVERS = {("wsnav.firmware", "testing"), ("wsnav.firmware", "unix_board")}
"""Modules the tests and benchmarks drive the MicroPython unix port with (and the reason for the firmware ->
broker arrow): part of the checkout, not of what a user installs. Whole packages are left out in pyproject.toml."""


class BuildPyWithoutTestDrivers(build_py):
    """setuptools' build_py, minus TEST_DRIVERS (packages.find can leave out packages only, not modules)."""

    def find_package_modules(self, package: str, package_dir: str) -> list[tuple[str, str, str]]:
        modules = super().find_package_modules(package, package_dir)
        return [m for m in modules if (m[0], m[1]) not in TEST_DRIVERS]


here = Path(__file__).resolve().parent
flat = sorted(
    p.name for p in (here / "wsnav").iterdir() if p.is_file() and not p.is_symlink() and not p.suffix
)
if flat:
    raise SystemExit(
        f"wsnav: cannot build: wsnav/{', wsnav/'.join(flat)} should be symbolic links to the top-level folders but "
        "are plain files (a checkout without symlinks; with Git: git config core.symlinks true, then check out again)"
    )
setup(cmdclass={"build_py": BuildPyWithoutTestDrivers})
