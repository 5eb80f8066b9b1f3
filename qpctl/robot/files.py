"""Robot files on disk: example-robot-data's files, package:// paths, and Pinocchio's model of a URDF or MJCF."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import pinocchio as pin

from qpctl.errors import ConfigError


def example_robot_data_path(relative: str) -> Path:
    """Absolute path of a file shipped by the installed ``example-robot-data`` package.

    ``relative`` is below the package's ``robots/`` folder, e.g. ``panda_description/urdf/panda.urdf``.
    """
    try:
        files = importlib.metadata.files("example-robot-data") or []
    except importlib.metadata.PackageNotFoundError as exc:
        raise ConfigError("the example-robot-data package is not installed (pip install example-robot-data)",
                          key="robot") from exc
    suffix = "example-robot-data/robots/" + relative
    for f in files:
        if str(f).replace("\\", "/").endswith(suffix):
            return Path(f.locate()).resolve()
    raise ConfigError(f"example-robot-data has no file {relative}", key="robot")


def read_model(path: Path, *, key: str) -> pin.Model:
    """Pinocchio's model of a URDF, or of an MJCF (``.xml``, ``.mjcf``); :class:`ConfigError` naming
    ``key`` if the file is missing or does not parse."""
    mjcf = path.suffix.lower() in (".xml", ".mjcf")
    if not path.is_file():
        raise ConfigError(f"{'MJCF' if mjcf else 'URDF'} not found: {path}", key=key)
    try:
        return pin.buildModelFromMJCF(str(path)) if mjcf else pin.buildModelFromUrdf(str(path))
    except (ValueError, RuntimeError) as exc:
        raise ConfigError(f"cannot parse {path.name}: {' '.join(str(exc).split())}", key=key) from None


def resolve_package_uri(path: str | Path) -> Path:
    """A path, with ``package://example-robot-data/robots/<file>`` read as that installed package's file."""
    text = str(path)
    prefix = "package://example-robot-data/robots/"
    if text.startswith(prefix):
        return example_robot_data_path(text[len(prefix):])
    if text.startswith("package://"):
        raise ConfigError(f"cannot resolve {text}: only package://example-robot-data/robots/... is known; give a path",
                          key="robot")
    return Path(path)


def package_dirs(path: str | Path) -> list[str]:
    """Where a robot file's ``package://`` meshes are looked for: example-robot-data's share folder
    (when installed) and every folder above the file."""
    dirs = [str(p) for p in Path(path).resolve().parents]
    try:
        dirs.insert(0, str(example_robot_data_path("panda_description/urdf/panda.urdf").parents[4]))
    except ConfigError:
        pass
    return dirs
