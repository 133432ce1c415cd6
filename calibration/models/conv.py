"""A small fully-convolutional network: a pixel's normal from the colour change around it.

A pixel's colour alone cannot undo what spreads light over its neighbours (an optical blur,
the gel's smoothing at the rim, printed markers, JPEG blocks); its neighbourhood can. The
network sees, per pixel, the colour change of every pattern-channel relative to the reference,
``2 (I - I_ref) / (I_ref + f)`` (``change="relative"``, the default; ``f`` is
:data:`RELATIVE_FLOOR` of ``input_scale``), the reference ``I_ref`` over ``input_scale`` and the
normalised position ``(u, v)``, as image planes. The relative change is the same wherever a
pixel's light is dimmed or brightened by the same factor in the frame and the reference
(vignetting, an LED's fall-off), so a press at a place the calibration never saw looks like the
presses it did see. ``change="difference"`` gives the MLP's input (:mod:`calibration.models.mlp`),
``4 (I - I_ref) / input_scale``, as networks stored before the relative change have it. A stack
of 3 x 3 convolutions with growing dilation (``dilations``, default 1, 2, 4, 8: a 31 x 31 pixel window)
and two 1 x 1 layers give ``(n_x, n_y)`` per pixel, with ``n_z = sqrt(1 - n_x^2 - n_y^2)``.
Every convolution is "valid"; a frame is padded by the window's radius, repeating its border
pixels, so a pixel's answer depends on its own window only: training on tiles of the presses
and predicting whole frames compute the same function.

Training: tiles of ``tile x tile`` output pixels centred on the presses' samples (three in four
on contact pixels, the rest on flat ones), each with its input window; the loss is the L1
error of ``(n_x, n_y)`` at the tile's sampled pixels, weighted toward the rim as the MLP's
(``rim_weight``); a weak colour change is lifted for training (``change_rms``, the gain then
folded into the first layer). Adam with a cosine learning-rate decay over ``epochs`` steps of ``batch``
tiles; the seed and ``torch.use_deterministic_algorithms`` make two fits bit-identical. The
samples must carry their whole frames (:attr:`calibration.samples.Samples.images`, as
:func:`calibration.samples.collect_samples` and :func:`calibration.normal_maps.pixel_samples`
give them).

``downsample``: the network sees the frame shrunk by that factor (the mean of each ``f x f``
block) and its ``(n_x, n_y)`` are brought back to every pixel bilinearly. A blurred sensor image
(the DIGIT's, a virtual sensor's) loses little. ``calibrate`` sizes it from the ball for the
default network (:func:`ball_downsample`: a window of about three quarters of the ball's radius);
the fast variant (:class:`ConvFastModel`, ``--model conv-fast``) always shrinks by 2, to run on a
quarter of the pixels.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from calibration.models.base import CalibrationModel, ensemble_arrays, ensemble_states, seeded_torch
from calibration.samples import Samples

__all__ = ["ConvModel", "ConvFastModel", "CONV_MODELS", "BALL_PX_PER_BLOCK", "CHANGES", "RELATIVE_FLOOR",
           "CHANGE_RMS", "ball_downsample", "feature_planes", "block_mean", "upsample_planes", "window_share"]

#: How the colour change enters the network (:func:`feature_planes`): ``relative`` to the
#: reference (the default) or the plain ``difference`` (networks stored before it).
CHANGES = ("relative", "difference")

#: Added to the reference under the relative change, as a share of ``input_scale`` (10 DN of an
#: 8-bit camera): a dark pixel (a printed marker, a vignetted corner) does not blow its change up.
RELATIVE_FLOOR = 10.0 / 255.0

#: The RMS the colour-change planes are brought to for training (over the drawn tiles, flat ones
#: included; ``change_rms`` of :class:`ConvModel`). A soft gel's shading changes the colour two to
#: three times less than a firm gel's, and a network whose first layer sees such small inputs
#: learns less from them in the same steps. The gain is folded into the first layer after
#: training, so the stored network takes the planes as :func:`feature_planes` gives them.
CHANGE_RMS = 0.3

#: The ball radius in pixels per block of :func:`ball_downsample`: the default network's window
#: (31 pixels) then spans about three quarters of the ball's radius on every sensor.
BALL_PX_PER_BLOCK = 40.0


def ball_downsample(ball_px: float) -> int:
    """The ``downsample`` of :class:`ConvModel` where the caller gives none: the frame shrunk so that
    the ball's radius is about :data:`BALL_PX_PER_BLOCK` blocks' pixels (at least 1).

    The window that helps depends on the contact's size in pixels (measured through the whole
    calibration, exact or test-press error): on the DIGIT (ball 113 px) 3.99 deg at 1 and 2.44 at 3;
    on virtual seed 3 (78 px) 2.41 at 1 and 2.20 at 2; on the shared GelSight (16 px) shrinking by 3
    gave 5.4 deg against 2.35 at 1 (docs/calibration.md, "The convolutional network").

    >>> ball_downsample(16.0), ball_downsample(54.0), ball_downsample(78.0), ball_downsample(113.0)
    (1, 1, 2, 3)
    """
    return max(1, int(round(float(ball_px) / BALL_PX_PER_BLOCK)))


def block_mean(a: np.ndarray, factor: int) -> np.ndarray:
    """``(..., H, W, C)`` shrunk by ``factor``: the mean of each ``factor x factor`` block (the
    last block row and column padded by repeating the border), shape ``(..., ceil(H/f), ceil(W/f), C)``.

    Examples
    --------
    >>> a = np.arange(12, dtype=np.float32).reshape(1, 3, 4, 1)
    >>> block_mean(a, 2)[0, ..., 0].tolist()
    [[2.5, 4.5], [8.5, 10.5]]
    """
    f = int(factor)
    a = np.asarray(a, np.float32)
    if f == 1:
        return a
    h, w = a.shape[-3:-1]
    ph, pw = -h % f, -w % f
    if ph or pw:
        pad = [(0, 0)] * (a.ndim - 3) + [(0, ph), (0, pw), (0, 0)]
        a = np.pad(a, pad, mode="edge")
    out = None
    for i in range(f):
        for j in range(f):
            part = a[..., i::f, j::f, :]
            out = part.copy() if out is None else np.add(out, part, out=out)
    return np.multiply(out, np.float32(1.0 / (f * f)), out=out)


def upsample_planes(planes, factor: int, shape: tuple[int, int]):
    """``(B, 2, h, w)`` torch planes of block centres to ``(B, 2, H, W)``, bilinear (block
    ``i`` of :func:`block_mean` is centred on pixel ``f i + (f - 1) / 2``), cut to ``shape``."""
    import torch

    f = int(factor)
    if f == 1:
        return planes
    up = torch.nn.functional.interpolate(planes, scale_factor=f, mode="bilinear", align_corners=False)
    return up[..., :shape[0], :shape[1]]


def window_share(shape: tuple[int, int], radius_px: int) -> np.ndarray:
    """The share of each pixel's input window (``2 radius_px + 1`` pixels a side) that lies inside the frame.

    A frame is padded by repeating its border pixels, so a pixel within ``radius_px`` of the
    border reads copies instead of what lies beyond it; the network's error there was measured
    at 2-3 times the interior's (docs/calibration.md, "The convolutional network"). Its
    confidence is this share: 1 away from the border, about a half at an edge, a quarter in a corner.

    Parameters
    ----------
    shape : (H, W)
    radius_px : int
        The window's radius in frame pixels.

    Returns
    -------
    ndarray, shape (H, W), float32

    Examples
    --------
    >>> share = window_share((5, 6), 2)
    >>> [round(float(v), 2) for v in share[2]], round(float(share[0, 0]), 2)
    ([0.6, 0.8, 1.0, 1.0, 0.8, 0.6], 0.36)
    """
    def axis(n: int) -> np.ndarray:
        i = np.arange(n)
        return (np.minimum(i, radius_px) + np.minimum(n - 1 - i, radius_px) + 1) / (2.0 * radius_px + 1.0)

    h, w = (int(v) for v in shape)
    if h < 1 or w < 1 or int(radius_px) < 0:
        raise ValueError(f"window_share: a frame of at least 1 x 1 and a radius >= 0 expected, got {shape}, {radius_px}")
    return np.outer(axis(h), axis(w)).astype(np.float32)


def feature_planes(image: np.ndarray, reference: np.ndarray, rows: tuple[int, int], cols: tuple[int, int],
                   input_scale: float, change: str = "relative") -> np.ndarray:
    """The network's input planes on a window of a frame.

    Parameters
    ----------
    image, reference : ndarray, shape (P, H, W, C)
        A frame and the no-contact reference (linear).
    rows, cols : (start, stop)
        The window (stop excluded); it may reach past the frame, whose border pixels then repeat.
    input_scale : float
    change : {"relative", "difference"}
        The colour change as ``2 (I - I_ref) / (I_ref + RELATIVE_FLOOR * input_scale)`` or as
        ``4 (I - I_ref) / input_scale`` (:data:`CHANGES`).

    Returns
    -------
    ndarray, shape (2 * P * C + 2, stop - start of rows, of cols), float32
        The colour change, the reference over ``input_scale``, then ``u``, ``v`` (the position,
        -1 to 1 over the frame).

    Examples
    --------
    >>> img = np.full((1, 4, 5, 3), 60.0, np.float32); ref = np.full((1, 4, 5, 3), 50.0, np.float32)
    >>> x = feature_planes(img, ref, (-1, 3), (0, 5), 100.0, change="difference")
    >>> x.shape, round(float(x[0, 0, 0]), 3), round(float(x[3, 0, 0]), 3), x[6, 0].tolist(), x[7, :, 0].tolist()
    ((8, 4, 5), 0.4, 0.5, [-1.0, -0.5, 0.0, 0.5, 1.0], [-1.0, -1.0, -0.3333333432674408, 0.3333333432674408])
    >>> round(float(feature_planes(img, ref, (0, 4), (0, 5), 255.0)[0, 0, 0]), 4)  # 2 x 10 / (50 + 10)
    0.3333
    """
    if change not in CHANGES:
        raise ValueError(f"feature_planes: change must be one of {CHANGES}, got {change!r}")
    p, h, w, c = image.shape
    (a, b), (d, e) = (int(v) for v in rows), (int(v) for v in cols)
    r0, r1, c0, c1 = max(a, 0), min(b, h), max(d, 0), min(e, w)
    if r0 >= r1 or c0 >= c1:
        raise ValueError(f"feature_planes: the window rows {rows}, cols {cols} misses the {h} x {w} frame")
    scale = np.float32(1.0 / float(input_scale))
    img = np.asarray(image, np.float32)[:, r0:r1, c0:c1].transpose(0, 3, 1, 2).reshape(p * c, r1 - r0, c1 - c0)
    ref = np.asarray(reference, np.float32)[:, r0:r1, c0:c1].transpose(0, 3, 1, 2).reshape(p * c, r1 - r0, c1 - c0)
    u = (np.clip(np.arange(d, e), 0, w - 1).astype(np.float32) - (w - 1) / 2.0) / max((w - 1) / 2.0, 1.0)
    v = (np.clip(np.arange(a, b), 0, h - 1).astype(np.float32) - (h - 1) / 2.0) / max((h - 1) / 2.0, 1.0)
    out = np.empty((2 * p * c + 2, b - a, e - d), np.float32)
    inner = (slice(r0 - a, r1 - a), slice(c0 - d, c1 - d))
    if change == "relative":  # written in place: this runs on every live frame
        dest = out[(slice(0, p * c), *inner)]
        np.subtract(img, ref, out=dest)
        dest *= np.float32(2.0)
        # a reference below zero (an offset removed upstream) would flip or blow up the ratio
        dest /= np.maximum(ref, np.float32(0.0)) + np.float32(RELATIVE_FLOOR * float(input_scale))
    else:
        np.multiply(img - ref, np.float32(4.0 * scale), out=out[(slice(0, p * c), *inner)])
    np.multiply(ref, scale, out=out[(slice(p * c, 2 * p * c), *inner)])
    planes = out[:2 * p * c]
    if (a, b, d, e) != (r0, r1, c0, c1):  # repeat the border pixels into the window's margin
        planes[:, :r0 - a] = planes[:, r0 - a:r0 - a + 1]
        planes[:, r1 - a:] = planes[:, r1 - a - 1:r1 - a]
        planes[:, :, :c0 - d] = planes[:, :, c0 - d:c0 - d + 1]
        planes[:, :, c1 - d:] = planes[:, :, c1 - d - 1:c1 - d]
    out[-2] = u[None, :]
    out[-1] = v[:, None]
    return out


def _change_planes(x: np.ndarray) -> int:
    """How many of the planes of ``x (N, F, ...)`` are the colour change: the first half of all
    but the last two (:func:`feature_planes`: the change, as many reference planes, then ``u, v``)."""
    return (x.shape[1] - 2) // 2


class ConvModel(CalibrationModel):
    """Fully-convolutional network on a pixel's neighbourhood.

    Parameters
    ----------
    width : int
        Channels of every hidden layer.
    dilations : tuple of int
        One 3 x 3 convolution per entry, with that dilation; the window's radius is their sum.
    epochs : int
        Adam steps (each on ``batch`` tiles). 1200 steps on 768 tiles (600 on 384 before): two fits
        of different seeds then differ less (virtual seeds 2 / 3, exact error through the whole
        calibration: 2.27, 2.28 / 2.12, 2.05 deg against 2.29, 2.49 / 2.24, 2.67), for twice the
        fit time (docs/calibration.md, "The convolutional network").
    lr : float
        Peak learning rate (cosine decay to 0).
    seed : int
    tile : int
        Output pixels per tile side.
    tiles : int
        Tiles drawn (seeded) from the training samples.
    batch : int
        Tiles per step.
    input_scale : float
        Camera values are divided by this (255 for 8-bit frames).
    rim_weight : float
        Loss weight of a contact pixel at the rim relative to the apex, ``1 + (rim_weight - 1)
        rho^2`` (as :class:`calibration.models.mlp.MLPModel`).
    device : str
        Torch device ("cpu", "cuda").
    threads : int or None
        Torch intra-op threads while fitting and predicting (None: leave torch's setting).
    members : int
        Ensemble size: members differ in seed (initial weights, drawn tiles and their order) and
        their ``(n_x, n_y)`` are averaged; fit and per-frame time grow ``members`` times. Two by
        default (the live variant, :class:`ConvFastModel`: one): on presses never seen, virtual
        seeds 2 / 3 (exact truth) 1.93 / 1.86 deg against 2.02 / 1.98 with one network
        (docs/calibration.md, "The convolutional network").
    downsample : int
        The network runs on the frame shrunk by this factor (:func:`block_mean`; the window,
        ``tile`` and the dilations are then in shrunk pixels) and its answer is brought back to
        every pixel bilinearly (:func:`upsample_planes`); 1: every pixel.
    change : {"relative", "difference"}
        The colour change it sees (:func:`feature_planes`). Relative to the reference, against
        the difference, on presses never seen (exact truth, one fit each, two network seeds):
        virtual seeds 0-3 1.68 / 1.47 / 2.08, 1.95 / 1.92, 1.99 deg against 1.81 / 1.56 / 2.26,
        2.32 / 2.24, 2.08; the shared GelSight 1.97 against 2.19 deg, the DIGIT 1.91 against
        1.98 deg (docs/calibration.md, "The convolutional network").
    change_rms : float or None
        For training, the colour-change planes are multiplied by the gain that brings their RMS
        over the drawn tiles to this (:data:`CHANGE_RMS`); the gain is folded into the first
        layer afterwards, so prediction and the stored arrays do not change. None: no gain.
        The fit's report gives each member's gain (``change_gain``). A floor, not a
        normalisation: on presses never seen (one fit each, exact truth) the soft look of
        virtual seed 2 gives 2.75 deg against 2.95 without it (gain 1.9), the plain seeds 2 / 3
        1.92 / 1.86 against 1.93 / 1.85; the shared GelSight's and DIGIT's planes are above it
        (gain 1: the very same networks), and lifting every sensor's to 0.5 moved those by
        +0.18 / +0.12 deg (docs/calibration.md, "A weak shading lifted for training").
    """

    name = "conv"
    confidence_meaning = ("the share of the network's input window inside the frame (1 away from the border, "
                          "about 0.5 at an edge), where it gives a normal; 0 where it gives none")
    #: No ball tilt gain (calibrate still measures and reports it). The network's tilts on presses
    #: it never saw are within a few per cent of right, less than what the gain measures wrongly:
    #: the gain comes from about ten held-out spheres that scatter by 5-10 % and from fold networks
    #: trained on four fifths of the presses, which shrink the tilts more than the final one.
    #: Measured through the whole calibration (test presses; exact truth on the virtual seeds),
    #: the ball's gain against none: DIGIT 2.44 deg and ball 5.8 % against 2.18 deg and 2.9 %;
    #: virtual seeds 1 / 2 / 3 2.54 / 2.11 / 2.20 against 1.70 / 2.29 / 2.24 deg; the shared
    #: GelSight 2.35 deg and 1.7 % against 2.07 deg and 0.9 % (docs/calibration.md, "The
    #: convolutional network").
    applies_tilt_gain = False

    def __init__(self, width: int = 16, dilations: tuple[int, ...] = (1, 2, 4, 8), epochs: int = 1200, lr: float = 1e-2,
                 seed: int = 0, tile: int = 16, tiles: int = 768, batch: int = 32, input_scale: float = 255.0,
                 rim_weight: float = 4.0, device: str = "cpu", threads: int | None = 1, downsample: int = 1,
                 members: int = 2, change: str = "relative", change_rms: float | None = CHANGE_RMS):
        dil = tuple(int(d) for d in dilations)
        if change_rms is not None and not float(change_rms) > 0:
            raise ValueError(f"ConvModel: change_rms must be > 0 or None, got {change_rms!r}")
        self.change_rms = None if change_rms is None else float(change_rms)
        if change not in CHANGES:
            raise ValueError(f"ConvModel: change must be one of {CHANGES}, got {change!r}")
        self.change = change
        if int(members) < 1:
            raise ValueError(f"ConvModel: members must be an integer >= 1, got {members}")
        self.members = int(members)
        if int(downsample) < 1:
            raise ValueError(f"ConvModel: downsample must be an integer >= 1, got {downsample}")
        self.downsample = int(downsample)
        if int(width) < 1 or not dil or min(dil) < 1:
            raise ValueError(f"ConvModel: width must be >= 1 and dilations a non-empty list of integers >= 1, got "
                             f"{width}, {dilations}")
        if int(tile) < 1 or int(tiles) < 1 or int(batch) < 1 or not rim_weight > 0:
            raise ValueError(f"ConvModel: tile, tiles and batch must be >= 1 and rim_weight > 0, got {tile}, {tiles}, "
                             f"{batch}, {rim_weight}")
        self.width, self.dilations, self.epochs, self.lr, self.seed = int(width), dil, int(epochs), float(lr), int(seed)
        self.tile, self.tiles, self.batch = int(tile), int(tiles), int(batch)
        self.input_scale, self.rim_weight = float(input_scale), float(rim_weight)
        self.device, self.threads = device, threads
        self.nets: list = []
        self.shape: tuple[int, int] | None = None
        self.reference: np.ndarray | None = None
        self._border_shares: dict[tuple[int, int, int], np.ndarray] = {}

    @property
    def net(self):
        """The first member (the only one unless ``members > 1``); None before fitting."""
        return self.nets[0] if self.nets else None

    @property
    def radius(self) -> int:
        """The input window's radius (pixels): the sum of the dilations."""
        return int(sum(self.dilations))

    def _build(self, n_in: int):
        import torch

        mods: list = []
        width = n_in
        for d in self.dilations:
            mods += [torch.nn.Conv2d(width, self.width, 3, dilation=d), torch.nn.SiLU()]
            width = self.width
        mods += [torch.nn.Conv2d(width, self.width, 1), torch.nn.SiLU(), torch.nn.Conv2d(self.width, 2, 1)]
        return torch.nn.Sequential(*mods).to(self.device)

    @staticmethod
    def _frames(samples: Samples) -> tuple[np.ndarray, np.ndarray]:
        if samples.images is None or samples.reference_image is None:
            raise ValueError("ConvModel: the samples carry no whole frames (Samples.images, reference_image); build "
                             "them with calibration.samples.collect_samples or calibration.normal_maps.pixel_samples")
        return samples.images, samples.reference_image

    @staticmethod
    def _flat_area(samples: Samples, idx: np.ndarray) -> np.ndarray:
        """``(H, W)`` float32, 1 on the flat gel of one frame: within 2 px of its flat samples (a sparse
        grid far from the contact, :func:`calibration.samples.collect_samples`), every pixel."""
        from scipy import ndimage

        out = np.zeros(samples.shape, bool)
        flat = idx[~samples.contact[idx]]
        out[samples.rows[flat], samples.cols[flat]] = True
        return ndimage.maximum_filter(out, size=5).astype(np.float32)

    def _tile_set(self, samples: Samples, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(inputs (N, F, T + 2R, T + 2R), targets (N, 2, T, T), weights (N, T, T))`` of the tiles drawn with ``seed``."""
        images, ref = self._frames(samples)
        rng = np.random.default_rng(seed)
        con = np.nonzero(samples.contact)[0]
        flat = np.nonzero(~samples.contact)[0]
        n_con = 0 if not len(con) else self.tiles if not len(flat) else int(round(0.75 * self.tiles))
        centres = np.concatenate([rng.choice(con, n_con) if n_con else np.zeros(0, int),
                                  rng.choice(flat, self.tiles - n_con) if self.tiles > n_con else np.zeros(0, int)])
        w_all = np.ones(len(samples), np.float32)
        if self.rim_weight != 1.0 and samples.radial is not None:
            rho2 = np.where(samples.contact, np.clip(samples.radial, 0.0, 1.0) ** 2, 0.0)
            w_all = (1.0 + (self.rim_weight - 1.0) * rho2).astype(np.float32)
        t, r = self.tile, self.radius
        by_press = {int(p): np.nonzero(samples.press == p)[0] for p in np.unique(samples.press[centres])}
        flat = {p: self._flat_area(samples, idx) for p, idx in by_press.items()}
        h, w = samples.shape
        n_in = 2 * int(np.prod(samples.intensities.shape[1:])) + 2
        x = np.empty((len(centres), n_in, t + 2 * r, t + 2 * r), np.float32)
        y = np.zeros((len(centres), 2, t, t), np.float32)
        wt = np.zeros((len(centres), t, t), np.float32)
        for j, i in enumerate(centres):
            p = int(samples.press[i])
            r0, c0 = int(samples.rows[i]) - t // 2, int(samples.cols[i]) - t // 2
            img = images[p] if p >= 0 else ref
            x[j] = feature_planes(img, ref, (r0 - r, r0 + t + r), (c0 - r, c0 + t + r), self.input_scale,
                                  self.change)
            win = flat[p][np.clip(np.arange(r0, r0 + t), 0, h - 1)][:, np.clip(np.arange(c0, c0 + t), 0, w - 1)]
            wt[j] = win  # the flat gel around the flat samples: n = (0, 0, 1)
            idx = by_press[p]
            rr, cc = samples.rows[idx] - r0, samples.cols[idx] - c0
            m = (rr >= 0) & (rr < t) & (cc >= 0) & (cc < t)
            y[j, :, rr[m], cc[m]] = samples.normals[idx[m], :2].astype(np.float32)
            wt[j, rr[m], cc[m]] = w_all[idx[m]]
        return x, y, wt

    def _shrunk(self, samples: Samples) -> Samples:
        """The samples on the frames shrunk by :attr:`downsample`, each pixel on its block."""
        f = self.downsample
        if f == 1:
            return samples
        images, ref = self._frames(samples)
        h, w = samples.shape
        return dataclasses.replace(samples, rows=samples.rows // f, cols=samples.cols // f,
                                   shape=(-(-h // f), -(-w // f)), images=block_mean(images, f),
                                   reference_image=block_mean(ref, f))

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        self.shape = samples.shape
        if reference is not None:
            self.reference = np.asarray(reference, dtype=np.float32)
        shrunk = self._shrunk(samples)
        self.nets, losses, gains, n_tiles = [], [], [], 0
        for i in range(self.members):  # members differ in seed: initial weights, drawn tiles, their order
            x, y, w = self._tile_set(shrunk, self.seed + i)
            gains.append(self._change_gain(x))
            net, loss = self._train(x, y, w, self.seed + i, gains[-1])
            self.nets.append(net)
            losses.append(loss)
            n_tiles = len(x)
        rep = self._fit_report(samples)
        rep["final_l1_loss"] = float(np.mean(losses))
        rep["tiles"] = int(n_tiles)
        rep["members"] = len(self.nets)
        rep["change_gain"] = gains
        return rep

    def _change_gain(self, x: np.ndarray) -> float:
        """The factor that lifts the colour-change planes of the tiles ``x`` to an RMS of
        :attr:`change_rms` where theirs is lower; 1 where it is not, or is None, or the planes are
        all zero."""
        rms = float(np.sqrt(np.mean(np.square(x[:, :_change_planes(x)], dtype=np.float64))))
        return 1.0 if self.change_rms is None or rms <= 0 else max(1.0, float(self.change_rms / rms))

    def _train(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, seed: int, change_gain: float = 1.0):
        """One network trained on the tiles ``x`` (targets ``y``, weights ``w``) with ``seed``, its
        colour-change planes multiplied by ``change_gain`` (in place; folded into the first layer
        afterwards: the network takes the planes unscaled); and its last loss."""
        import torch

        w = w / max(float(w.sum()) / max(int((w > 0).sum()), 1), 1e-12)  # mean weight 1 over the sampled pixels
        n_change = _change_planes(x)
        x[:, :n_change] *= np.float32(change_gain)
        with seeded_torch(seed, self.threads):
            net = self._build(x.shape[1])
            xt, yt, wt = (torch.from_numpy(a).to(self.device) for a in (x, y, w))
            opt = torch.optim.Adam(net.parameters(), lr=self.lr)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(self.epochs, 1))
            order = np.random.default_rng(seed + 1)
            perm = order.permutation(len(x))
            at, loss = 0, torch.zeros(())
            for _ in range(self.epochs):
                if at + self.batch > len(perm):
                    perm, at = order.permutation(len(x)), 0
                b = torch.from_numpy(perm[at:at + self.batch])
                at += self.batch
                opt.zero_grad()
                wb = wt[b]
                loss = (wb[:, None] * (net(xt[b]) - yt[b]).abs()).sum() / torch.clamp(wb.sum() * 2, min=1e-6)
                loss.backward()
                opt.step()
                sched.step()
            with torch.no_grad():  # W (g c) = (g W) c: the stored network takes the planes unscaled
                net[0].weight[:, :n_change] *= change_gain
        return net.eval(), float(loss.detach())

    def predict_planes(self, image: np.ndarray, reference: np.ndarray, rows: slice, cols: slice,
                       as_float64: bool = True) -> np.ndarray:
        """The raw ``(n_x, n_y)`` ``(2, h, w)`` on a window (``rows``, ``cols`` slices) of a frame
        (float64, or the network's float32 with ``as_float64=False``)."""
        import torch

        if not self.nets:
            raise ValueError("ConvModel: not fitted")
        r = self.radius
        x = feature_planes(image, reference, (rows.start - r, rows.stop + r), (cols.start - r, cols.stop + r),
                           self.input_scale, self.change)
        from pipeline.base.threads import limit_threads

        # No deterministic mode here: it picks slower convolutions (45 against 17 ms a 320 x 240
        # frame, measured), and inference on a CPU gives the same numbers run after run.
        with torch.no_grad(), limit_threads(torch=int(self.threads) if self.threads else None):
            xt = torch.from_numpy(x[None]).to(self.device)
            out = self.nets[0](xt)
            for net in self.nets[1:]:
                out += net(xt)
            if len(self.nets) > 1:
                out /= len(self.nets)
            out = out[0].cpu().numpy()
        return out.astype(np.float64) if as_float64 else out

    def frame_planes(self, image: np.ndarray, reference: np.ndarray,
                     shrunk_reference: np.ndarray | None = None) -> np.ndarray:
        """The raw ``(n_x, n_y)`` ``(2, H, W)`` float32 of a whole frame ``(P, H, W, C)``: with
        :attr:`downsample` > 1 the network's answer on the shrunk frame, brought back to every
        pixel (``shrunk_reference``: the reference already shrunk, :func:`block_mean`)."""
        import torch

        h, w = image.shape[1:3]
        f = self.downsample
        if f == 1:
            return self.predict_planes(image, reference, slice(0, h), slice(0, w), as_float64=False)
        ref = block_mean(reference, f) if shrunk_reference is None else shrunk_reference
        img = block_mean(image, f)
        lo = self.predict_planes(img, ref, slice(0, img.shape[1]), slice(0, img.shape[2]), as_float64=False)
        with torch.no_grad():
            return upsample_planes(torch.from_numpy(lo[None]), f, (h, w))[0].numpy()

    def _predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        images, ref = self._frames(samples)
        out = np.zeros((len(samples), 2))
        ref_lo = block_mean(ref, self.downsample)
        for p in np.unique(samples.press):
            m = samples.press == p
            rows, cols = samples.rows[m], samples.cols[m]
            img = images[p] if p >= 0 else ref
            if self.downsample > 1:  # the whole frame: shrunk, through the network, brought back
                out[m] = self.frame_planes(img, ref, ref_lo)[:, rows, cols].T
                continue
            r0, c0 = int(rows.min()), int(cols.min())
            planes = self.predict_planes(img, ref, slice(r0, int(rows.max()) + 1), slice(c0, int(cols.max()) + 1))
            out[m] = planes[:, rows - r0, cols - c0].T
        r2 = np.sum(out ** 2, axis=1)
        # Outputs outside the unit disc have no normal: shrink them onto an 85-degree tilt (as the MLP).
        out = out * np.where(r2 > 0.996, np.sqrt(0.996 / np.maximum(r2, 1e-12)), 1.0)[:, None]
        n = np.concatenate([out, np.sqrt(1.0 - np.sum(out ** 2, axis=1, keepdims=True))], axis=1)
        ok = np.isfinite(n).all(axis=1)
        return n, ok, np.where(ok, self.border_share(samples.shape)[samples.rows, samples.cols], 0.0)

    def border_share(self, shape: tuple[int, int]) -> np.ndarray:
        """:func:`window_share` of this network's window (its radius times :attr:`downsample`) on a frame of ``shape``
        (kept per shape: building it took 0.7 ms of a 320 x 240 frame, the fast network's 8.5)."""
        key = (int(shape[0]), int(shape[1]), self.radius * self.downsample)
        if key not in self._border_shares:
            self._border_shares[key] = window_share(key[:2], key[2])
        return self._border_shares[key]

    def normal_maps(self, frames: np.ndarray, reference: np.ndarray | None = None, *, markers=None):
        """Normals, mask and confidence of whole frames, as
        :func:`calibration.normal_maps.predict_normal_maps` gives them (which runs with ``markers``).

        Without markers the network runs on each whole frame in float32 and its answer is corrected
        (``tilt_gain``, ``max_tilt``) in place: the same normals as the per-sample path to float32
        rounding, without gathering every pixel as a sample (86 -> 50 ms a 320 x 240 frame, measured
        with other jobs running).
        """
        from calibration.normal_maps import NormalMaps, as_frame_stack

        ref = reference if reference is not None else self.stored_reference()
        if markers is not None or ref is None:
            return super().normal_maps(frames, reference, markers=markers)
        ref = np.asarray(ref, np.float32)
        stack = as_frame_stack(frames, ref.shape[0])
        n_img, p, h, w, c = stack.shape
        if ref.shape != (p, h, w, c):
            raise ValueError(f"ConvModel.normal_maps: reference must be (P, H, W, C) = {(p, h, w, c)} like the frames, "
                             f"got {ref.shape}")
        # One sum tells a frame without a NaN or an infinity (the usual case): the per-pixel tests of
        # the frame and of the normals took 4.5 ms of a 320 x 240 frame (measured, a loaded machine).
        if np.isfinite(np.sum(stack)):
            finite = np.ones((n_img, h, w), bool)
        else:
            finite = np.isfinite(stack).all(axis=(1, 4))
            stack = np.where(np.isfinite(stack), stack, np.float32(0.0))
        normals = np.zeros((n_img, h, w, 3), np.float32)
        limit = np.float32(0.999 if self.max_tilt is None else min(float(self.max_tilt), 0.999))
        ref_lo = block_mean(ref, self.downsample)
        tiny, gain = np.float32(1e-12), np.float32(self.tilt_gain)
        for i in range(n_img):
            xy = self.frame_planes(stack[i], ref, ref_lo)
            r = np.sqrt(xy[0] * xy[0] + xy[1] * xy[1])
            # One scale per pixel: onto an 85-degree tilt at most (as _predict), the output
            # correction (scale_tilt), then its largest tilt.
            scale = np.minimum(np.float32(np.sqrt(0.996)) / np.maximum(r, tiny), np.float32(1.0))
            scale *= gain
            r *= scale
            np.minimum(scale, scale * (limit / np.maximum(r, tiny)), out=scale)
            np.minimum(r, limit, out=r)
            normals[i, ..., 0] = xy[0] * scale
            normals[i, ..., 1] = xy[1] * scale
            normals[i, ..., 2] = np.sqrt(np.maximum(np.float32(1.0) - r * r, np.float32(0.0)))
        mask = finite if np.isfinite(np.sum(normals)) else finite & np.isfinite(normals).all(-1)
        if not mask.all():
            normals[~mask] = (0.0, 0.0, 1.0)
        return NormalMaps(normals=normals, mask=mask, confidence=mask * self.border_share((h, w)),
                          meta={"model": self.name, "confidence": self.confidence_meaning})

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays for calibration.h5 (inverse: :meth:`from_arrays`): ``weights/<param>`` (the first
        member), ``members/<i>/<param>`` (the others), ``config = [width, *dilations]``,
        ``input_scale``, ``downsample``, ``members``, ``change`` (the index of :attr:`change` in
        :data:`CHANGES`), ``reference``."""
        if not self.nets:
            raise ValueError("ConvModel: not fitted")
        arrays = ensemble_arrays(self.nets)
        arrays["config"] = np.array([self.width, *self.dilations], dtype=np.int64)
        arrays["input_scale"] = np.asarray(self.input_scale, dtype=np.float64)
        arrays["downsample"] = np.asarray(self.downsample, dtype=np.int64)
        arrays["members"] = np.asarray(len(self.nets), dtype=np.int64)
        arrays["change"] = np.asarray(CHANGES.index(self.change), dtype=np.int64)
        if self.reference is not None:
            arrays["reference"] = self.reference
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], device: str = "cpu") -> "ConvModel":
        """A fitted model from :meth:`to_arrays`' output (files written before ensembles, or before
        the relative change: those networks saw the difference, and keep seeing it, load too)."""

        cfg = [int(v) for v in np.asarray(arrays["config"]).ravel()]
        members = int(arrays.get("members", 1))
        code = int(arrays.get("change", CHANGES.index("difference")))
        if not 0 <= code < len(CHANGES):
            raise ValueError(f"ConvModel.from_arrays: 'change' must index {CHANGES}, got {code}")
        model = cls(width=cfg[0], dilations=tuple(cfg[1:]), input_scale=float(arrays["input_scale"]), device=device,
                    downsample=int(arrays.get("downsample", 1)), members=members, change=CHANGES[code])
        ref = arrays.get("reference")
        model.reference = None if ref is None else np.asarray(ref, np.float32)
        if model.reference is not None:
            model.shape = tuple(model.reference.shape[1:3])
        for state in ensemble_states(arrays, members):
            net = model._build(int(state["0.weight"].shape[1]))
            net.load_state_dict(state)
            model.nets.append(net.eval())
        return model


class ConvFastModel(ConvModel):
    """The network on the frame shrunk by 2 (``--model conv-fast``, ``--solver conv-fast``).

    :class:`ConvModel` with ``downsample=2``, dilations 1, 2, 4 (a 15 x 15 window of shrunk
    pixels: about the 31 x 31 pixel window of the full network) and one network, on a quarter of
    the pixels: the live choice where the full network is too slow (docs/calibration.md, "The
    convolutional network"). Every option of :class:`ConvModel` applies.
    """

    name = "conv-fast"

    def __init__(self, width: int = 16, dilations: tuple[int, ...] = (1, 2, 4), downsample: int = 2,
                 members: int = 1, **options):
        super().__init__(width=width, dilations=dilations, downsample=downsample, members=members, **options)


#: The networks by model name (``--model``, ``models/<name>/`` in calibration.h5).
CONV_MODELS = {cls.name: cls for cls in (ConvModel, ConvFastModel)}
