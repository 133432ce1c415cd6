"""What a real tactile sensor adds to its frames besides the physics: numpy in, numpy out.

Each function is one effect of :mod:`sim.virtual_sensor`, called only when a sensor turns
it on (so a sensor that asks for less costs less):

- :func:`marker_coverage`: printed dots on the gel (dark albedo), as the fraction of each
  pixel they cover (supersampled), and from it the exact marker mask;
- :func:`drift_basis` / :func:`drift_field`: a smooth low-order multiplicative field
  (illumination drift between the reference and a press);
- :func:`apply_drift`: per-channel gain and offset and that field, on linear DN;
- :func:`column_stripes`: per-column offsets redrawn every frame (the stripes of cheap
  rolling-shutter sensors such as the DIGIT's);
- :func:`displace_markers` and :func:`dot_coverage`: printed dots moved by a press, as a real
  gel stretched by the ball carries them;
- :func:`soften_shading` and :func:`rim_highlight`: a soft gel's weak, broad shading with a
  glossy highlight where the contact's rim faces a light;
- :func:`quantize_8bit` and :func:`jpeg_roundtrip`: what the camera stores;
- :func:`optical_blur`: the lens and gel stack's point spread (a Gaussian), as on the DIGIT.

Images are ``(H, W, 3)`` RGB; linear ones float (DN), stored ones uint8.
"""

from __future__ import annotations

import numpy as np

__all__ = ["marker_coverage", "drift_basis", "drift_field", "apply_drift", "column_stripes", "quantize_8bit",
           "jpeg_roundtrip", "optical_blur", "DRIFT_TERMS", "dot_coverage", "displace_markers", "soften_shading",
           "rim_highlight"]

#: Terms of the drift field, on coordinates u (columns) and v (rows) scaled to [-1, 1].
DRIFT_TERMS = ("u", "v", "u^2", "uv", "v^2")


def marker_coverage(shape: tuple[int, int], spacing_px: float, radius_px: float, *, angle_deg: float = 0.0,
                    jitter_px: float = 0.0, offset_px: tuple[float, float] = (0.0, 0.0), rng=None,
                    supersample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Printed round markers on a (rotated, jittered) square grid.

    Parameters
    ----------
    shape : (H, W)
    spacing_px, radius_px : float
        Grid pitch and dot radius in pixels (``radius_px < spacing_px / 2``).
    angle_deg : float
        Grid rotation.
    jitter_px : float
        Each dot moved by up to this much (uniform) in x and y (needs ``rng``).
    offset_px : (float, float)
        Grid origin (x, y) relative to the image centre.
    supersample : int
        Subsamples per pixel side for the coverage.

    Returns
    -------
    coverage : ndarray, shape (H, W), float32
        Fraction of each pixel inside a dot, in [0, 1].
    centers_xy : ndarray, shape (N, 2)
        Dot centres (x = column, y = row) in pixels.

    Examples
    --------
    >>> cov, c = marker_coverage((30, 30), 10.0, 2.0)
    >>> cov.shape, len(c), round(float(cov.sum()) / len(c), 1)   # about pi r^2 = 12.6 per dot
    ((30, 30), 9, 13.0)
    """
    h, w = int(shape[0]), int(shape[1])
    if not 0 < radius_px < spacing_px / 2:
        raise ValueError(f"marker_coverage: need 0 < radius_px < spacing_px / 2, got radius {radius_px}, "
                         f"spacing {spacing_px}")
    if jitter_px > 0 and rng is None:
        raise ValueError("marker_coverage: jitter_px > 0 needs an rng")
    a = np.deg2rad(angle_deg)
    cx, cy = (w - 1) / 2 + offset_px[0], (h - 1) / 2 + offset_px[1]
    n = int(np.ceil(np.hypot(h, w) / spacing_px / 2)) + 1
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    gx, gy = i.ravel() * spacing_px, j.ravel() * spacing_px
    x = cx + gx * np.cos(a) - gy * np.sin(a)
    y = cy + gx * np.sin(a) + gy * np.cos(a)
    if jitter_px > 0:
        x = x + rng.uniform(-jitter_px, jitter_px, x.shape)
        y = y + rng.uniform(-jitter_px, jitter_px, y.shape)
    keep = (x > -radius_px) & (x < w - 1 + radius_px) & (y > -radius_px) & (y < h - 1 + radius_px)
    centers = np.stack([x[keep], y[keep]], axis=-1)
    return dot_coverage((h, w), centers, radius_px, supersample=supersample), centers


def dot_coverage(shape: tuple[int, int], centers_xy: np.ndarray, radius_px: float, *, supersample: int = 4
                 ) -> np.ndarray:
    """Fraction of each pixel ``(H, W)`` (float32) covered by round dots of ``radius_px`` at ``centers_xy (N, 2)``.

    Examples
    --------
    >>> cov = dot_coverage((20, 20), np.array([[10.0, 10.0]]), 3.0)
    >>> round(float(cov.sum()), 0), float(cov[10, 10]), float(cov[0, 0])
    (28.0, 1.0, 0.0)
    """
    h, w = int(shape[0]), int(shape[1])
    cov = np.zeros((h, w), np.float32)
    s = int(supersample)
    sub = (np.arange(s) + 0.5) / s - 0.5  # subsample offsets within a pixel
    for mx, my in np.asarray(centers_xy, np.float64).reshape(-1, 2):
        r0, r1 = max(0, int(np.floor(my - radius_px))), min(h, int(np.ceil(my + radius_px)) + 1)
        c0, c1 = max(0, int(np.floor(mx - radius_px))), min(w, int(np.ceil(mx + radius_px)) + 1)
        if r0 >= r1 or c0 >= c1:
            continue
        yy = (np.arange(r0, r1)[:, None] + sub[None, :]).reshape(-1)
        xx = (np.arange(c0, c1)[:, None] + sub[None, :]).reshape(-1)
        inside = ((yy[:, None] - my) ** 2 + (xx[None, :] - mx) ** 2) <= radius_px ** 2
        frac = inside.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3))
        cov[r0:r1, c0:c1] = np.maximum(cov[r0:r1, c0:c1], frac)
    return cov


def drift_basis(shape: tuple[int, int]) -> np.ndarray:
    """The drift field's terms :data:`DRIFT_TERMS` as ``(5, H, W)`` float32, u and v in [-1, 1].

    Examples
    --------
    >>> b = drift_basis((3, 5))
    >>> b.shape, b[0, 0].tolist(), b[1, :, 0].tolist()
    ((5, 3, 5), [-1.0, -0.5, 0.0, 0.5, 1.0], [-1.0, 0.0, 1.0])
    """
    h, w = int(shape[0]), int(shape[1])
    u = np.linspace(-1.0, 1.0, w) if w > 1 else np.zeros(1)
    v = np.linspace(-1.0, 1.0, h) if h > 1 else np.zeros(1)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv, uu * uu, uu * vv, vv * vv]).astype(np.float32)


def drift_field(shape: tuple[int, int], coeffs) -> np.ndarray:
    """``1 + sum_i coeffs[i] * term_i`` over :func:`drift_basis`: ``(H, W)`` float32.

    Examples
    --------
    >>> f = drift_field((3, 5), [0.1, 0, 0, 0, 0])
    >>> [round(float(v), 3) for v in f[0]]
    [0.9, 0.95, 1.0, 1.05, 1.1]
    """
    c = np.asarray(coeffs, np.float32).reshape(-1)
    if c.shape != (len(DRIFT_TERMS),):
        raise ValueError(f"drift_field: coeffs must have {len(DRIFT_TERMS)} terms {DRIFT_TERMS}, got {c.shape}")
    return 1.0 + np.tensordot(c, drift_basis(shape), axes=1)


def apply_drift(image: np.ndarray, gain=None, offset=None, field=None) -> np.ndarray:
    """``gain_c * field(x) * I_c(x) + offset_c`` on a linear image ``(H, W, 3)`` (any of them may be None).

    Examples
    --------
    >>> img = np.full((2, 2, 3), 100.0, np.float32)
    >>> apply_drift(img, gain=[1.1, 1.0, 0.9], offset=[0, 5, -5])[0, 0].tolist()
    [110.0, 105.0, 85.0]
    """
    out = np.asarray(image, np.float32)
    if out.ndim != 3:
        raise ValueError(f"apply_drift: image must be (H, W, C), got {out.shape}")
    if field is not None:
        out = out * np.asarray(field, np.float32)[..., None]
    if gain is not None:
        out = out * np.asarray(gain, np.float32)
    if offset is not None:
        out = out + np.asarray(offset, np.float32)
    return out


def column_stripes(shape: tuple[int, int], sigma_dn: float, rng) -> np.ndarray:
    """Per-column offsets ``(H, W, 1)`` (DN), Gaussian with ``sigma_dn``, the same down each column.

    Examples
    --------
    >>> s = column_stripes((4, 6), 2.0, np.random.default_rng(0))
    >>> s.shape, bool(np.all(s[0] == s[3]))
    ((4, 6, 1), True)
    """
    h, w = int(shape[0]), int(shape[1])
    col = rng.normal(0.0, float(sigma_dn), w).astype(np.float32)
    return np.broadcast_to(col[None, :, None], (h, w, 1))


def quantize_8bit(image: np.ndarray) -> np.ndarray:
    """Round and clip linear DN to uint8.

    Examples
    --------
    >>> quantize_8bit(np.array([[[-3.0, 100.4, 300.0]]])).tolist()
    [[[0, 100, 255]]]
    """
    return np.clip(np.round(np.asarray(image, np.float32)), 0, 255).astype(np.uint8)


def jpeg_roundtrip(image: np.ndarray, quality: int) -> tuple[np.ndarray, bytes]:
    """Encode an RGB uint8 image as JPEG (OpenCV, 4:2:0 chroma as cameras do) and decode it again.

    Returns the decoded image and the JPEG bytes (write those to a ``.jpg`` to store exactly
    what the decoded image holds, without compressing twice).

    Examples
    --------
    >>> img = np.zeros((16, 16, 3), np.uint8); img[:, 8:] = (200, 40, 10)
    >>> dec, data = jpeg_roundtrip(img, 50)
    >>> dec.shape, data[:2] == b"\\xff\\xd8", int(np.abs(dec.astype(int) - img).max()) > 0
    ((16, 16, 3), True, True)
    """
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"jpeg_roundtrip: expected an RGB uint8 image (H, W, 3), got {img.dtype} {img.shape}")
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"jpeg_roundtrip: quality must be in 1..100, got {quality}")
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 RGB image
        raise RuntimeError("jpeg_roundtrip: OpenCV could not encode the image")
    data = buf.tobytes()
    dec = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(dec[..., ::-1]), data


def optical_blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """A linear image ``(H, W, C)`` blurred by a Gaussian of standard deviation ``sigma_px``.

    The optics' point spread: a camera focused behind a thick gel (the DIGIT's frames are
    blurred by about 11 px, docs/calibration.md). The border is mirrored, so a flat image
    stays flat.

    Examples
    --------
    >>> img = np.zeros((9, 9, 3), np.float32); img[4, 4] = 90.0
    >>> out = optical_blur(img, 1.0)
    >>> out.shape, round(float(out[..., 0].sum()), 3), bool(out[4, 4, 0] < 90)
    ((9, 9, 3), 90.0, True)
    """
    import cv2

    img = np.asarray(image, np.float32)
    if img.ndim != 3:
        raise ValueError(f"optical_blur: image must be (H, W, C), got {img.shape}")
    if not sigma_px >= 0:
        raise ValueError(f"optical_blur: sigma_px must be >= 0, got {sigma_px}")
    if sigma_px == 0:
        return img
    k = 2 * int(np.ceil(4 * sigma_px)) + 1
    out = cv2.GaussianBlur(img, (k, k), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    return out.reshape(img.shape)


def displace_markers(centers_xy: np.ndarray, contact_xy, contact_radius_px: float, amplitude_px: float
                     ) -> np.ndarray:
    """Dot centres moved by a press: radially outward, ``amplitude_px * rho / a`` inside the contact
    (radius ``a``) and ``amplitude_px * (a / rho)^2`` beyond it (the gel stretched over the ball
    and pushed aside around it).

    Examples
    --------
    >>> c = np.array([[10.0, 0.0], [5.0, 0.0], [20.0, 0.0]])
    >>> displace_markers(c, (0.0, 0.0), 10.0, 2.0)[:, 0].round(3).tolist()
    [12.0, 6.0, 20.5]
    """
    c = np.asarray(centers_xy, np.float64).reshape(-1, 2)
    d = c - np.asarray(contact_xy, np.float64)
    rho = np.hypot(d[:, 0], d[:, 1])
    a = float(contact_radius_px)
    mag = np.where(rho <= a, amplitude_px * rho / max(a, 1e-9), amplitude_px * (a / np.maximum(rho, 1e-9)) ** 2)
    unit = d / np.maximum(rho, 1e-9)[:, None]
    return c + unit * mag[:, None]


def soften_shading(image: np.ndarray, reference: np.ndarray, contrast: float, blur_px: float) -> np.ndarray:
    """A soft gel's shading: the change from ``reference`` scaled by ``contrast`` and blurred (Gaussian,
    ``blur_px``), on linear images ``(H, W, 3)``.

    Examples
    --------
    >>> ref = np.full((9, 9, 3), 100.0, np.float32); img = ref.copy(); img[4, 4] = 190.0
    >>> out = soften_shading(img, ref, 0.5, 0.0)
    >>> float(out[4, 4, 0]), float(out[0, 0, 0])
    (145.0, 100.0)
    """
    from scipy import ndimage

    ref = np.asarray(reference, np.float32)
    change = (np.asarray(image, np.float32) - ref) * float(contrast)
    if blur_px > 0:
        change = ndimage.gaussian_filter(change, (blur_px, blur_px, 0))
    return ref + change


def rim_highlight(normals: np.ndarray, tilt_deg: float, azimuth_deg: float, strength_dn: float,
                  sharpness: float) -> np.ndarray:
    """A white glossy highlight ``strength_dn * max(0, n . h)^sharpness`` ``(H, W, 1)`` float32.

    ``h`` leans ``tilt_deg`` from the camera axis toward ``azimuth_deg`` (on screen,
    counter-clockwise from the right; reconstruction-frame normals ``(H, W, 3)``): the highlight
    sits where the contact's sphere cap is tilted that much toward that light, a crescent near
    its rim, and nowhere on flat gel (for a sharp lobe).

    Examples
    --------
    >>> n = np.zeros((1, 2, 3)); n[..., 2] = 1.0
    >>> t = np.deg2rad(20.0); n[0, 1] = (np.sin(t), 0.0, np.cos(t))
    >>> [round(float(v), 1) for v in rim_highlight(n, 20.0, 0.0, 100.0, 80.0)[0, :, 0]]
    [0.7, 100.0]
    """
    t, a = np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg)
    h = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    dot = np.clip(np.asarray(normals, np.float64) @ h, 0.0, 1.0)
    return (float(strength_dn) * dot ** float(sharpness)).astype(np.float32)[..., None]
