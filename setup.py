"""Refuses to build from a checkout without symbolic links: wsnav/<component> link to the top-level folders, and a
checkout that made them one-line text files (Git for Windows' default, core.symlinks=false) built a wheel of 10
files that said nothing and failed at run time (`ModuleNotFoundError: wsnav.runtime`). Everything else is in
pyproject.toml."""

from pathlib import Path

from setuptools import setup

here = Path(__file__).resolve().parent
flat = sorted(
    p.name for p in (here / "wsnav").iterdir() if p.is_file() and not p.is_symlink() and not p.suffix
)
if flat:
    raise SystemExit(
        f"wsnav: cannot build: wsnav/{', wsnav/'.join(flat)} should be symbolic links to the top-level folders but "
        "are plain files (a checkout without symlinks; with Git: git config core.symlinks true, then check out again)"
    )
setup()
