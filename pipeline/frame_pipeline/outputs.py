"""What a reconstruction writes: the one owner of the output datasets, their precision and layout.

Always written: the normals and their validity mask (the ``normals`` entry), the heights and
theirs (the ``depth`` entry). The rest is a choice (:data:`OUTPUT_CHOICES`, ``--save``):

========== ============================== ==================== =================================
name       what                           bytes a pixel        default
========== ============================== ==================== =================================
confidence the calibration models' own    4 (2 at half)        ``reconstruct`` yes (where the solver
           rating of each normal                               gives one), ``batch`` no
contact    where the object touches the   1                    ``reconstruct`` yes, ``batch`` no
           gel (its own ``contact`` entry)                     (about 10 ms a 320 x 240 frame)
albedo     per-channel albedo             4 a channel          no
residual   RMS residual of the solve      4                    no
condition  the light matrix's condition   4                    no
count      observations used              4                    no
========== ============================== ==================== =================================

Precision (``--precision``): ``single`` (float32, the default) or ``half`` (the normals and the
confidence as float16: 6 instead of 12 bytes a pixel for the normals, a quantisation of at most
0.03 deg; heights stay float32, their scale is the gel's). At 320 x 240 the default writes 1.7 MB
a frame with a calibration model's confidence (1.4 MB without), 1.1 MB at half precision.

The choice is part of the stage keys (:func:`pipeline.stages.normals.params`): the same work is
one cache entry whichever command asked for it.

Examples
--------
>>> spec = OutputSpec.parse("contact,albedo", "half")
>>> spec.normal_extras, spec.contact, spec.normals_dtype
(('albedo',), True, dtype('float16'))
>>> OutputSpec.parse("shape")
Traceback (most recent call last):
...
pipeline.base.errors.UserError: --save: unknown output 'shape' (choose from confidence, contact, albedo, residual, \
condition, count, all, none)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["OUTPUT_CHOICES", "NORMAL_EXTRAS", "PRECISIONS", "OutputSpec", "DEFAULT_RECONSTRUCT", "DEFAULT_BATCH"]

#: The normals record's datasets beyond the normals and their mask, written only when asked.
NORMAL_EXTRAS = ("albedo", "residual", "condition", "count")

#: What ``--save`` names (besides ``all`` and ``none``).
OUTPUT_CHOICES = ("confidence", "contact", *NORMAL_EXTRAS)

#: ``--precision`` choices: the normals' and the confidence's float type.
PRECISIONS = {"single": np.dtype(np.float32), "half": np.dtype(np.float16)}

#: ``--save`` defaults of the two commands that write results: a one-off reconstruction gets the
#: contact mask and the models' confidence; a recording, where disk bandwidth bounds the run (two
#: threads at 320 x 240 on a 2-core machine: 263 frames/s with neither, 193 with the confidence,
#: docs/reconstruction.md "Batch"), the normals and heights with their masks.
DEFAULT_RECONSTRUCT = "confidence,contact"
DEFAULT_BATCH = "none"


@dataclass(frozen=True)
class OutputSpec:
    """A choice of outputs (see the module docstring).

    Attributes
    ----------
    confidence, contact : bool
    normal_extras : tuple of str
        Of :data:`NORMAL_EXTRAS`, in that order.
    precision : str
        A key of :data:`PRECISIONS`.
    """

    confidence: bool = True
    contact: bool = False
    normal_extras: tuple[str, ...] = ()
    precision: str = "single"

    @classmethod
    def parse(cls, save: str | None = None, precision: str = "single") -> OutputSpec:
        """From ``--save`` (comma-separated names of :data:`OUTPUT_CHOICES`, ``all`` or ``none``;
        None: :data:`DEFAULT_RECONSTRUCT`) and ``--precision``."""
        names = [s.strip() for s in (DEFAULT_RECONSTRUCT if save is None else save).split(",") if s.strip()]
        if "all" in names:
            names = list(OUTPUT_CHOICES)
        names = [n for n in names if n != "none"]
        for n in names:
            if n not in OUTPUT_CHOICES:
                raise UserError(f"--save: unknown output {n!r} (choose from {', '.join(OUTPUT_CHOICES)}, all, none)")
        if precision not in PRECISIONS:
            raise UserError(f"--precision: {precision!r} is not one of {', '.join(PRECISIONS)}")
        return cls(confidence="confidence" in names, contact="contact" in names,
                   normal_extras=tuple(n for n in NORMAL_EXTRAS if n in names), precision=str(precision))

    @property
    def normals_dtype(self) -> np.dtype:
        """The normals' (and the confidence's) float type."""
        return PRECISIONS[self.precision]

    def key_params(self) -> dict:
        """What enters the normals key (the contact mask is an entry of its own; the normals stage
        drops ``confidence`` for solvers that give none)."""
        return {"save": list(self.normal_extras) + (["confidence"] if self.confidence else []),
                "precision": self.precision}

    def names(self) -> list[str]:
        """The chosen names, for messages and JSON."""
        return ((["confidence"] if self.confidence else []) + (["contact"] if self.contact else [])
                + list(self.normal_extras))

    def normals_datasets(self, shape: tuple[int, int], groups: int, has_confidence: bool) -> dict[str, tuple]:
        """The ``normals`` entry's per-frame datasets: name -> (frame shape, dtype)."""
        H, W = shape
        out: dict[str, tuple] = {"normals": ((H, W, 3), self.normals_dtype), "mask": ((H, W), np.bool_)}
        if self.confidence and has_confidence:
            out["confidence"] = ((H, W), self.normals_dtype)
        extra = {"albedo": ((H, W, groups), np.float32), "residual": ((H, W), np.float32),
                 "condition": ((H, W), np.float32), "count": ((H, W), np.int32)}
        out.update({n: extra[n] for n in self.normal_extras})
        return out

    @staticmethod
    def depth_datasets(shape: tuple[int, int]) -> dict[str, tuple]:
        """The ``depth`` entry's per-frame datasets."""
        return {"height": (tuple(shape), np.float32), "mask": (tuple(shape), np.bool_)}

    @staticmethod
    def contact_datasets(shape: tuple[int, int]) -> dict[str, tuple]:
        """The ``contact`` entry's per-frame datasets."""
        return {"contact": (tuple(shape), np.bool_)}
