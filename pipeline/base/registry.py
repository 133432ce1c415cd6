"""The registries of interchangeable parts: photometric-stereo solvers and depth integrators.

Each registry is the one list of its names. The command line takes its choices from it
(``--solver``, ``--integrator``), the run config's schema gets its ``enum`` from it
(``x-choices`` in ``data_schemas/configs/pipeline.json``), and ``reconstruct``, ``batch``,
``compare-modes`` and the normals and depth stages look names up in it. Registering a new
solver or integrator is one :class:`Entry` here.

An entry names its implementation lazily, as ``"package.module:attribute"``, imported only
when it is used: listing the choices (``iristac --help``) stays fast, and this base layer
never imports the layers above it.

Lighting modes are data, not code: a built-in mode registers by its YAML file in
:data:`MODES_DIR` (``pipeline/base/modes/``), listed by :func:`list_modes` and read by
:func:`pipeline.base.modes.load_mode`.

Examples
--------
>>> SOLVERS.names()
('lstsq', 'nearfield', 'robust', 'cauchy', 'far', 'near', 'traced', 'lut', 'mlp', 'conv', 'conv-fast')
>>> INTEGRATORS.check("dst")
'dst'
>>> INTEGRATORS.check("poisson")
Traceback (most recent call last):
...
pipeline.base.errors.UserError: --integrator must be one of fc, dct, dst, sparse, got 'poisson'
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from pipeline.base.errors import UserError

__all__ = ["Entry", "Registry", "SOLVERS", "INTEGRATORS", "MODES_DIR", "list_modes"]


@dataclass(frozen=True)
class Entry:
    """One registered implementation.

    Attributes
    ----------
    name : str
        What users type (``--solver NAME``) and what enters stage keys.
    target : str
        ``"package.module:attribute"`` of the implementation, imported by :meth:`load`.
    summary : str
        One line for ``--help`` and the docs.
    info : mapping
        Facts the callers need without importing the implementation (for a solver: the
        lights it ``needs`` and the ``patterns`` it takes).
    """

    name: str
    target: str
    summary: str = ""
    info: Mapping[str, Any] = field(default_factory=dict)

    def load(self) -> Any:
        """Import and return the implementation."""
        module, _, attr = self.target.partition(":")
        return getattr(importlib.import_module(module), attr)


class Registry:
    """An ordered set of :class:`Entry`, looked up by name.

    Parameters
    ----------
    kind : str
        What the entries are (``solver``), for messages.
    flag : str
        The command-line option that picks one (``--solver``), named in errors.
    entries : sequence of Entry
        In the order ``--help`` lists them; the first is not implied to be the default.
    """

    def __init__(self, kind: str, flag: str, entries: Sequence[Entry] = ()):
        self.kind = kind
        self.flag = flag
        self._entries: dict[str, Entry] = {}
        for e in entries:
            self.register(e)

    def register(self, entry: Entry) -> Entry:
        """Add ``entry`` (a name may be registered once)."""
        if entry.name in self._entries:
            raise ValueError(f"{self.kind} {entry.name!r} is registered twice")
        if ":" not in entry.target:
            raise ValueError(f"{self.kind} {entry.name!r}: target must be 'module:attribute', got {entry.target!r}")
        self._entries[entry.name] = entry
        return entry

    def names(self) -> tuple[str, ...]:
        """The registered names, in registration order."""
        return tuple(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[Entry]:
        return iter(self._entries.values())

    def __len__(self) -> int:
        return len(self._entries)

    def check(self, name: str) -> str:
        """``name`` if registered, else a :class:`UserError` naming the flag and the choices."""
        if name not in self._entries:
            raise UserError(f"{self.flag} must be one of {', '.join(self._entries)}, got {name!r}")
        return name

    def get(self, name: str) -> Entry:
        """The entry of ``name`` (:class:`UserError` as in :meth:`check` when unknown)."""
        return self._entries[self.check(name)]

    def load(self, name: str) -> Any:
        """The implementation of ``name``, imported now."""
        return self.get(name).load()

    def fast(self, name: str) -> Any | None:
        """The builder of the fast per-frame path ``name`` registers (``info["fast"]``, imported
        now), or None when it has none.

        Examples
        --------
        >>> SOLVERS.fast("robust") is None, INTEGRATORS.fast("dst").__name__
        (True, 'FastDST')
        """
        target = self.get(name).info.get("fast")
        return None if not target else Entry(f"{name}-fast", target).load()

    def help(self) -> str:
        """``name: summary`` for every entry, for ``--help``."""
        return "; ".join(f"{e.name}: {e.summary}" if e.summary else e.name for e in self)


#: Photometric-stereo solvers: ``target(frames, lights, **options) -> list[NormalResult]`` (see
#: :func:`pipeline.normals.solve.solve_capture`). ``info``, the facts callers need without
#: importing the solver:
#:
#: - ``needs``: the lights the solver uses (``vectors``: far-field vectors or a light field,
#:   ``field``: per-pixel light vectors, ``model:NAME``: the calibration's fitted model NAME,
#:   applied through its batched ``normal_maps`` exactly as ``iristac eval calibration`` does);
#: - ``patterns``: ``any``, or ``one-rgb`` for a solver that reads one RGB frame per contact;
#: - ``variant``: an alternative that comparisons leave out unless asked for by name;
#: - ``whole_frame``: the solver reads whole frames (pixel positions are inputs) and is masked
#:   after, not gathered (:class:`pipeline.normals.prepare.FramePrep`);
#: - ``fills_markers``: the solver fills printed markers in itself (given the marker mask);
#:   the others get frames filled in by :class:`~pipeline.normals.prepare.FramePrep`;
#: - ``keys_on_reference``: the solver keys on the no-contact reference, or was calibrated on
#:   presses mapped onto its lighting (a calibration's models): each frame set's illumination
#:   drift against it is removed first by default (``--drift auto``,
#:   :meth:`pipeline.normals.prepare.FramePrep.use_drift`);
#: - ``fast``: the builder of its live per-frame path (precomputed once per calibration,
#:   :func:`pipeline.solving.frame_solvers.frame_solver`), absent when live use runs it eagerly;
#: - ``batch``: that fast path also solves many frames in one call per thread
#:   (:meth:`pipeline.normals.fast.NearFieldFast.solve_batch`), which the normals stage uses
#:   with more than one thread;
#: - ``numpy_on_cpu``: the solver computes with numpy on the CPU (torch only on another device
#:   or with ``compile``): torch is not imported, and the solve's thread limit is on BLAS
#:   (:class:`pipeline.normals.solve.FrameSolver`).
SOLVERS = Registry("solver", "--solver", [
    Entry("lstsq", "pipeline.normals.solve:stack_lstsq",
          "far field (Woodham): one light vector per observation, else the light field at the image centre",
          {"needs": "vectors", "patterns": "any", "fast": "pipeline.solving.frame_solvers:fast_lstsq", "batch": True,
           "numpy_on_cpu": True}),
    Entry("nearfield", "pipeline.normals.solve:stack_nearfield",
          "per-pixel light vectors (an illumination model or a calibrated light field)",
          {"needs": "field", "patterns": "any", "fast": "pipeline.solving.frame_solvers:fast_nearfield",
           "batch": True}),
    Entry("robust", "pipeline.normals.solve:stack_robust",
          "shadows and highlights modelled: attached shadows from the light matrix, highlights above and cast "
          "shadows below the Lambertian prediction rejected (Tukey IRLS); light field if present, else far field",
          {"needs": "vectors", "patterns": "any"}),
    Entry("cauchy", "pipeline.normals.solve:stack_cauchy",
          "the earlier robust solver: dark and saturated observations excluded, trimmed start, Cauchy IRLS",
          {"needs": "vectors", "patterns": "any", "variant": True}),
    Entry("far", "pipeline.solving.model_solvers:stack_far",
          "the calibration's far-field model (one light vector per pattern-channel, flat field from the reference), "
          "as eval calibration applies it",
          {"needs": "model:far", "keys_on_reference": True, "patterns": "any", "whole_frame": True,
           "fills_markers": True}),
    Entry("near", "pipeline.solving.model_solvers:stack_near",
          "the calibration's polynomial near-field model, as eval calibration applies it",
          {"needs": "model:near", "keys_on_reference": True, "patterns": "any", "whole_frame": True,
           "fills_markers": True}),
    Entry("traced", "pipeline.solving.model_solvers:stack_traced",
          "the calibration's traced model (ray-traced LED fields with fitted gains), as eval calibration applies it",
          {"needs": "model:traced", "keys_on_reference": True, "patterns": "any", "whole_frame": True,
           "fills_markers": True}),
    Entry("lut", "pipeline.solving.model_solvers:stack_lut",
          "the calibration's colour lookup table with its per-bin position correction (one RGB pattern)",
          {"needs": "model:lut", "keys_on_reference": True, "patterns": "one-rgb", "whole_frame": True,
           "fills_markers": True, "fast": "pipeline.solving.frame_solvers:fast_lut"}),
    Entry("mlp", "pipeline.solving.model_solvers:stack_mlp",
          "the calibration's MLP (colour change, reference and position -> normal)",
          {"needs": "model:mlp", "keys_on_reference": True, "patterns": "any", "whole_frame": True,
           "fills_markers": True, "fast": "pipeline.solving.frame_solvers:fast_mlp"}),
    Entry("conv", "pipeline.solving.model_solvers:stack_conv",
          "the calibration's convolutional network (the colour change around each pixel -> normal)",
          {"needs": "model:conv", "keys_on_reference": True, "patterns": "any", "whole_frame": True,
           "fills_markers": True}),
    Entry("conv-fast", "pipeline.solving.model_solvers:stack_conv_fast",
          "the calibration's convolutional network on the frame shrunk by 2, its normals brought back bilinearly "
          "(the live choice: 3-4 times faster than conv at 320 x 240)",
          {"needs": "model:conv-fast", "keys_on_reference": True, "patterns": "any", "whole_frame": True,
           "fills_markers": True}),
])

#: Depth integrators: ``target(normals (H, W, 3), mm_per_px, mask, **kwargs) -> DepthResult``
#: (see :func:`pipeline.depth.integrate`). ``info["fast"]``: the builder of its live per-frame
#: path, ``builder(shape, mm_per_px, workers=1)`` with ``integrate(normals, mask)``
#: (:func:`pipeline.depth.frame_integrator`), absent when live use runs it eagerly.
INTEGRATORS = Registry("integrator", "--integrator", [
    Entry("fc", "pipeline.depth.fourier:frankot_chellappa", "Frankot-Chellappa FFT projection (periodic)"),
    Entry("dct", "pipeline.depth.poisson:poisson_dct", "Poisson, Neumann border (DCT)"),
    Entry("dst", "pipeline.depth.poisson:poisson_dst", "Poisson, zero height on the border (DST)",
          {"fast": "pipeline.depth.fast:FastDST"}),
    Entry("sparse", "pipeline.depth.sparse:sparse_lstsq", "least squares on the valid pixels only (PCG)"),
])

#: Folder of the built-in lighting-mode files (schema ``data_schemas/configs/mode.json``).
MODES_DIR = Path(__file__).resolve().parent / "modes"


def list_modes() -> list[str]:
    """Names of the built-in lighting modes (the files in :data:`MODES_DIR`).

    Examples
    --------
    >>> {"point", "monochromatic", "trichromatic", "multicolour"} <= set(list_modes())
    True
    """
    return sorted(p.stem for p in MODES_DIR.glob("*.yaml"))
