"""A robot's SRDF: the link pairs its ``<disable_collisions>`` elements exempt from self-collision checks.

MoveIt's setup assistant writes them (reasons "Adjacent", "Never", "Default", "Always"), and
example-robot-data ships SRDFs beside its URDFs (``<robot>_description/srdf/<name>.srdf``).
:func:`disabled_pairs` reads them; :func:`find_srdf` finds the file beside a URDF. Which capsule
pairs the self-collision barrier then keeps is :mod:`qpctl.geometry.self_collision`'s business.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Collection
from pathlib import Path

from qpctl.errors import ConfigError

LinkPair = frozenset[str]


def disabled_pairs(path: str | Path, links: Collection[str], *, key: str = "robot.srdf") -> frozenset[LinkPair]:
    """The link pairs of the SRDF's ``<disable_collisions link1= link2=>`` elements.

    :class:`ConfigError` naming ``key`` if the file is missing or does not parse, an element lacks a
    link, or names a link that is not among ``links`` (the model's; the message lists them).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"SRDF not found: {path}", key=key)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ConfigError(f"{path.name} is not valid XML: {exc}", key=key) from None
    known = set(links)
    out = set()
    for k, el in enumerate(root.iter("disable_collisions")):
        a, b = el.get("link1"), el.get("link2")
        if not a or not b:
            raise ConfigError(f"{path.name}: disable_collisions #{k} needs link1 and link2", key=key)
        for name in (a, b):
            if name not in known:
                raise ConfigError(f"{path.name} names link {name!r}, which the model lacks; its links: "
                                  f"{', '.join(sorted(known))}", key=key)
        if a != b:
            out.add(frozenset((a, b)))
    return frozenset(out)


def find_srdf(urdf: str | Path) -> Path | None:
    """The SRDF beside a URDF — ``<folder>/../srdf/<name>.srdf`` (example-robot-data's layout; for
    ``ur5_robot.urdf`` also ``ur5.srdf``) or ``<folder>/<name>.srdf`` — or None."""
    urdf = Path(urdf)
    names = dict.fromkeys([urdf.stem, urdf.stem.removesuffix("_robot")])
    for folder in (urdf.parent.parent / "srdf", urdf.parent):
        for name in names:
            if (folder / f"{name}.srdf").is_file():
                return folder / f"{name}.srdf"
    return None
