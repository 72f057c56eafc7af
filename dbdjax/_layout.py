"""`envs/` and `training/` are top-level folders of the repository (design.md) that an installed
dbdjax maps into the package as `dbdjax.envs` and `dbdjax.training` (pyproject.toml,
`[tool.setuptools.package-dir]`). This module gives a source checkout that is not installed (or
one imported through PYTHONPATH while another checkout is installed) the same names, pointing
at the folders next to *this* `dbdjax/`, so code and tests import `dbdjax.envs` either way.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys
from pathlib import Path

# Sub-package name -> folder name at the repository root.
SOURCE_FOLDERS = {"dbdjax.envs": "envs", "dbdjax.training": "training"}


class _SourceFolderFinder(importlib.abc.MetaPathFinder):
    """Finds exactly the names in `folders` (fullname -> package folder); nothing else."""

    def __init__(self, folders: dict[str, Path]):
        self.folders = folders

    def find_spec(self, fullname, path=None, target=None):
        folder = self.folders.get(fullname)
        if folder is None:
            return None
        return importlib.util.spec_from_file_location(
            fullname, folder / "__init__.py", submodule_search_locations=[str(folder)]
        )


def map_source_folders() -> None:
    """Install the finder when this package sits in a source checkout (a pyproject.toml next to
    it) whose root has the folders; an installed package has them inside it and needs nothing."""
    root = Path(__file__).resolve().parent.parent
    if not (root / "pyproject.toml").is_file():
        return
    folders = {name: root / folder for name, folder in SOURCE_FOLDERS.items()}
    folders = {name: folder for name, folder in folders.items() if (folder / "__init__.py").is_file()}
    if not folders or any(isinstance(finder, _SourceFolderFinder) for finder in sys.meta_path):
        return
    # First in line: an editable install of another checkout would otherwise map these names to
    # its own folders while `dbdjax` itself comes from this one.
    sys.meta_path.insert(0, _SourceFolderFinder(folders))
