"""The package as pip builds it from pyproject.toml."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed_for_the_wheel():
    """setuptools ships only the packages pyproject.toml lists: an unlisted one works
    in an editable install and is missing from a wheel."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed, mapped = set(tool["packages"]), tool.get("package-dir", {})
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "mitsuba_active").rglob("__init__.py")}
    for name, folder in mapped.items():  # packages kept elsewhere in the repository
        found |= {".".join((name, *p.parent.relative_to(ROOT / folder).parts))
                  for p in (ROOT / folder).rglob("__init__.py")}
    assert found - listed == set(), sorted(found - listed)
