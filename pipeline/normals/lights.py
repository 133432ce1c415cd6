"""The light model a reconstruction uses, and which registered solvers it can drive.

:class:`LightSource` holds whatever the light file gave (far-field vectors, a per-pixel light
field with its flat field, a calibration's fitted models) and owns the rules that read it:
what it offers in the terms of a solver's ``needs`` (:meth:`LightSource.kinds`), the far-field
vectors a far-field solver uses (:meth:`LightSource.far_vectors`: the calibrated ones, else
the light field at the image centre) and the same lights on a region's pixels only
(:meth:`LightSource.gathered`). :func:`check_lights` is the one check that a solver of
:data:`pipeline.base.registry.SOLVERS` gets the lights it needs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.registry import SOLVERS

__all__ = ["LightSource", "applicable_solvers", "check_lights", "check_light_count"]


@dataclass
class LightSource:
    """The light model a reconstruction uses.

    Attributes
    ----------
    far : ndarray, shape (P, C, 3), optional
        One light vector per pattern-channel.
    field : ndarray, shape (P, C, H, W, 3), optional
        Per-pixel light vectors (``H, W``: the frames', or a region's ``1, M`` once
        :meth:`gathered`).
    flat_field : ndarray, shape (P, C, H, W), optional
        Observations are divided by it before solving (goes with ``field``).
    models : dict, optional
        A calibration's fitted models, name -> object with ``normal_maps(frames, reference,
        markers=...)`` (:func:`calibration.stored.calibration_from_record`).
    markers : ndarray, shape (H, W), bool, optional
        The printed gel markers the calibration found (the default marker mask of frames
        reconstructed with it).
    source : str
        Where the lights came from (for the record's attributes).
    key : str
        Identity of the light file (enters the normals stage key).
    centre : ndarray, shape (P, C, 3), optional
        The full frame's light field at the image centre, kept by :meth:`gathered` when the
        centre itself is no longer among the pixels.

    Examples
    --------
    >>> field = np.zeros((1, 3, 5, 7, 3)); field[:, :, 2, 3] = [0.0, 0.0, 1.0]
    >>> lights = LightSource(field=field)
    >>> lights.far_vectors()[0, 0].tolist(), sorted(lights.kinds())
    ([0.0, 0.0, 1.0], ['field', 'vectors'])
    """

    far: np.ndarray | None = None
    field: np.ndarray | None = None
    flat_field: np.ndarray | None = None
    models: dict[str, Any] | None = None
    markers: np.ndarray | None = None
    source: str = ""
    key: str = ""
    centre: np.ndarray | None = None

    def stored_reference(self, solver: str) -> np.ndarray | None:
        """The no-contact reference ``(P, H, W, C)`` (linear, float32) that ``solver``'s
        calibration model stores (the LUT's and the MLP's: what they key on without a capture's
        own), else None."""
        model = (self.models or {}).get(solver)
        ref = model.stored_reference() if model is not None and hasattr(model, "stored_reference") else None
        return None if ref is None else np.asarray(ref, np.float32)

    def kinds(self) -> set[str]:
        """What these lights offer, in the terms of a solver's ``needs``."""
        out = set()
        if self.far is not None or self.field is not None:
            out.add("vectors")
        if self.field is not None:
            out.add("field")
        out.update(f"model:{name}" for name in (self.models or {}))
        return out

    def far_vectors(self) -> np.ndarray | None:
        """``(P, C, 3)``: the far-field vectors, else the light field at the image centre (what a
        far-field calibration would measure there); None when the lights have neither."""
        if self.far is not None:
            return self.far
        if self.centre is not None:
            return self.centre
        if self.field is None:
            return None
        H, W = self.field.shape[2:4]
        return self.field[:, :, H // 2, W // 2, :]

    def gathered(self, pixels) -> LightSource:
        """These lights on the pixels of ``pixels`` (a :class:`~pipeline.normals.masking.PixelMask`):
        per-pixel fields gathered to ``(..., 1, M, ...)``, far-field vectors unchanged, the
        image centre's vectors kept."""
        if self.field is None:
            return self
        return replace(self, centre=self.far_vectors() if self.far is None else self.centre,
                       field=pixels.gather(self.field, axis=2),
                       flat_field=None if self.flat_field is None else pixels.gather(self.flat_field, axis=2))


def applicable_solvers(patterns: int, channels: int, kinds: set[str], variants: bool = False) -> tuple[str, ...]:
    """The registered solvers that can solve ``patterns`` x ``channels`` observations with lights
    offering ``kinds`` (:meth:`LightSource.kinds`), in registry order; ``variants`` includes the
    entries marked as alternatives (``info["variant"]``).

    Examples
    --------
    >>> applicable_solvers(24, 3, {"vectors", "field"})
    ('lstsq', 'nearfield', 'robust')
    >>> applicable_solvers(1, 3, {"vectors", "field", "model:lut"})
    ('lstsq', 'nearfield', 'robust', 'lut')
    """
    return tuple(e.name for e in SOLVERS if e.info.get("needs") in kinds
                 and (variants or not e.info.get("variant"))
                 and (e.info.get("patterns", "any") != "one-rgb" or (patterns == 1 and channels == 3)))


def check_lights(solver: str, lights: LightSource, P: int, C: int) -> None:
    """One clear :class:`~pipeline.base.errors.UserError` unless ``lights`` give ``solver`` what it
    ``needs`` for ``P`` patterns of ``C`` channels (see :data:`pipeline.base.registry.SOLVERS`).

    Examples
    --------
    >>> check_lights("lut", LightSource(far=np.eye(3)[None], source="cal.h5"), 1, 3)
    Traceback (most recent call last):
    ...
    pipeline.base.errors.UserError: --solver lut needs a calibration with the lookup table fitted (models/lut/*); \
cal.h5 has none (fit it with iristac calibrate --model)
    """
    info = SOLVERS.get(solver).info
    needs = info.get("needs") or ""
    if needs.startswith("model:") and needs[6:] not in (lights.models or {}):
        have = ", ".join(lights.models or {}) or "none"
        what = {"lut": "the lookup table", "mlp": "the MLP", "far": "the far-field model",
                "near": "the near-field model", "traced": "the traced model"}.get(needs[6:], "the model")
        raise UserError(f"--solver {solver} needs a calibration with {what} fitted (models/{needs[6:]}/*); "
                        f"{lights.source or 'the light source'} has {have} (fit it with iristac calibrate --model)")
    if info.get("patterns") == "one-rgb" and (P != 1 or C != 3):
        raise UserError(f"--solver {solver} needs one RGB pattern per frame, the capture has P={P}, C={C}")
    if needs == "field" and lights.field is None:
        raise UserError(f"--solver {solver} needs per-pixel lights (an illumination file or a calibration "
                        f"with light_field); {lights.source} has only far-field light vectors")
    if needs in ("vectors", "field") and lights.field is None and lights.far is None:
        raise UserError(f"--solver {solver} needs light vectors; {lights.source} has only fitted models "
                        f"({', '.join(lights.models or {})}): use --solver with one of them")
    if needs in ("vectors", "field"):
        check_light_count(None if lights.far is None else lights.far.reshape(P * C, 3), P, C,
                          lights.source or "the light source")


def check_light_count(far, P: int, C: int, source: str) -> None:
    """One clear error when the lights cannot determine a normal anywhere: fewer than three
    observations, or far-field light vectors ``far (P*C, 3)`` (None: per-pixel lights only)
    that span fewer than three directions."""
    if P * C < 3:
        raise UserError(f"{source}: {P} pattern(s) x {C} channel(s) = {P * C} observations; photometric stereo "
                        f"needs at least 3 lights")
    if far is not None:
        L = np.asarray(far)
        ok = np.isfinite(L).all(-1)
        sv = np.linalg.svd(L[ok].astype(np.float64), compute_uv=False) if ok.any() else np.zeros(1)
        rank = int((sv > 1e-6 * sv.max()).sum()) if sv.max() > 0 else 0  # 1e-6: float32-stored lights
        if rank < 3:
            raise UserError(f"{source}: the {P * C} light vectors span {rank} independent direction(s); "
                            f"photometric stereo needs at least 3 lights in different directions")
