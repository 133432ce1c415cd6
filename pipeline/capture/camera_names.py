"""Find a camera by its name, as gs_sdk does: ``/dev/v4l/by-id`` on Linux.

udev names every video device there after its USB descriptor, e.g.
``usb-GelSight_Inc._GelSight_Mini_R0B_28J2-CWXU-video-index0 -> ../../video2``: a symlink to
the device node. :func:`find_camera` matches a name pattern against those names (case
insensitive; ``_`` and spaces are the same; a part of the name, which may hold ``*``/``?``), keeps
one device per physical camera (``video-index0``, the capture node; ``index1`` is metadata),
and refuses an ambiguous pattern by listing what it matched. :func:`resolve_camera_source`
leaves an OpenCV index, a device path, a URL or a file as they are and resolves anything else
as a name, so ``iristac live --camera "GelSight Mini"`` works.

Examples
--------
>>> import os, tempfile
>>> d = tempfile.mkdtemp(); dev = os.path.join(d, "video2"); open(dev, "w").close()
>>> os.symlink(dev, os.path.join(d, "usb-GelSight_Inc._GelSight_Mini_R0B-video-index0"))
>>> m = find_camera("gelsight mini", by_id_dir=d)
>>> os.path.basename(m.device), m.index
('video2', 2)
"""

from __future__ import annotations

import fnmatch
import os
import re
from dataclasses import dataclass
from pathlib import Path

from pipeline.base.errors import UserError

__all__ = ["CameraMatch", "find_camera", "list_cameras", "resolve_camera_source", "BY_ID_DIR"]

#: Where udev lists video devices by name.
BY_ID_DIR = "/dev/v4l/by-id"


@dataclass(frozen=True)
class CameraMatch:
    """A camera found by name: its by-id ``name``, the ``link`` and the ``device`` it points to
    (``/dev/videoN``), and ``index`` N (what OpenCV's ``VideoCapture(N)`` opens)."""

    name: str
    link: str
    device: str
    index: int | None


def _norm(text: str) -> str:
    return re.sub(r"[\s_]+", " ", text).strip().lower()


def list_cameras(by_id_dir: str | os.PathLike = BY_ID_DIR) -> list[CameraMatch]:
    """Every capture node named in ``by_id_dir`` (``...-video-index0``, or names without an index)."""
    d = Path(by_id_dir)
    if not d.is_dir():
        return []
    out = []
    for link in sorted(d.iterdir()):
        m = re.search(r"-video-index(\d+)$", link.name)
        if m is not None and m[1] != "0":
            continue  # metadata nodes of the same camera
        device = os.path.realpath(link)
        num = re.search(r"(\d+)$", os.path.basename(device))
        out.append(CameraMatch(link.name, str(link), device, int(num[1]) if num else None))
    return out


def find_camera(pattern: str, by_id_dir: str | os.PathLike = BY_ID_DIR) -> CameraMatch:
    """The one camera whose by-id name matches ``pattern`` (see the module docstring).

    Raises
    ------
    UserError
        No by-id folder (no cameras, or not Linux), no match (the names present are listed),
        or several cameras match (listed: use a longer part of the name, e.g. the serial).
    """
    cams = list_cameras(by_id_dir)
    if not cams:
        raise UserError(f"camera {pattern!r}: no cameras named in {by_id_dir} (none plugged in, or not Linux); give "
                        "--camera an OpenCV index or a device path instead")
    want = _norm(pattern)
    glob = any(ch in pattern for ch in "*?[")
    hits = [c for c in cams if (fnmatch.fnmatchcase(_norm(c.name), f"*{want}*") if glob else want in _norm(c.name))]
    if not hits:
        raise UserError(f"camera {pattern!r}: no camera of that name in {by_id_dir}; cameras here: "
                        f"{', '.join(c.name for c in cams)}")
    devices = {c.device for c in hits}
    if len(devices) > 1:
        raise UserError(f"camera {pattern!r} matches {len(devices)} cameras: {', '.join(c.name for c in hits)}; use a "
                        "longer part of the name (the serial number tells two of one model apart)")
    return hits[0]


def resolve_camera_source(source, by_id_dir: str | os.PathLike = BY_ID_DIR):
    """What OpenCV should open for ``--camera SOURCE``: an index (``int``), a path, a URL or a file
    name (``clip.avi``) as given; anything else is a camera name (:func:`find_camera`), returned
    as its device path.

    Examples
    --------
    >>> resolve_camera_source("0"), resolve_camera_source("rtsp://cam/1"), resolve_camera_source("clip.avi")
    (0, 'rtsp://cam/1', 'clip.avi')
    """
    if isinstance(source, int):
        return source
    text = str(source)
    if text.isdigit():
        return int(text)
    looks_like_file = os.sep in text or re.fullmatch(r"\.[A-Za-z0-9]{1,5}", Path(text).suffix) is not None
    if "://" in text or os.path.exists(text) or looks_like_file:
        return text  # OpenCV opens it (or says it cannot)
    return find_camera(text, by_id_dir).device
