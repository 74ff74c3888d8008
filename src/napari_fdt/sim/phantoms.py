"""Refractive-index test scenes, returned as contrast volumes ``Δn = n − n_b`` (n_slices, H, W), float32.

Slice 0 is nearest the sources; pixel (i, j) of a slice sits at ``y = (i − H//2)·dx``,
``x = (j − W//2)·dx``; slice k's centre at height ``(k + 1/2)·Δz`` above the volume's bottom face.
"""

from __future__ import annotations

import numpy as np

from napari_fdt.errors import FDTInputError
from napari_fdt.sim.font import glyph

__all__ = ["text_phantom", "bead_phantom", "cell_phantom", "fibre_phantom", "SCENES"]


def _check_shape(shape: tuple[int, int], n_slices: int) -> tuple[int, int]:
    h, w = (int(s) for s in shape)
    if h < 8 or w < 8:
        raise FDTInputError("shape", f"must be at least 8×8 pixels, got {h}×{w}", "use a larger --shape")
    if n_slices < 1:
        raise FDTInputError("n_slices", f"must be >= 1, got {n_slices}", "use a positive --n-slices")
    return h, w


def _render_glyph(char: str, height_px: int, supersample: int = 4) -> np.ndarray:
    """Anti-aliased glyph, float in [0, 1], shape (height_px, round(height_px·5/7))."""
    bitmap = glyph(char).astype(np.float32)
    width_px = max(1, round(height_px * 5 / 7))
    hs, ws = height_px * supersample, width_px * supersample
    rows = np.minimum((np.arange(hs) * 7) // hs, 6)
    cols = np.minimum((np.arange(ws) * 5) // ws, 4)
    fine = bitmap[rows][:, cols]
    return fine.reshape(height_px, supersample, width_px, supersample).mean(axis=(1, 3))


def text_phantom(
    shape: tuple[int, int],
    n_slices: int,
    text: str = "UCDAVIS",
    delta_n: float = 0.05,
    letter_height_px: int | None = None,
    every: int = 2,
    first_slice: int = 0,
) -> np.ndarray:
    """Letters of ``text``, one per slice on slices ``first_slice, first_slice + every, …``, centred.

    Like the paper's validation scene: the other slices stay empty. Letters beyond the last slice are
    dropped. ``letter_height_px`` defaults to 40 % of the smaller image side.
    """
    h, w = _check_shape(shape, n_slices)
    if every < 1:
        raise FDTInputError("every", f"must be >= 1, got {every}", "letters go on every n-th slice")
    if not text.strip():
        raise FDTInputError("text", "is empty", "give at least one letter")
    height = int(letter_height_px or max(7, round(0.4 * min(h, w))))
    if height > h:
        raise FDTInputError("letter_height_px", f"{height} exceeds the image height {h}", "use smaller letters")
    vol = np.zeros((n_slices, h, w), dtype=np.float32)
    chars = [c for c in text if not c.isspace()]
    for j, c in enumerate(chars):
        k = first_slice + j * every
        if k >= n_slices:
            break
        g = _render_glyph(c, height)
        gh, gw = g.shape
        gw = min(gw, w)
        r0, c0 = (h - gh) // 2, (w - gw) // 2
        vol[k, r0 : r0 + gh, c0 : c0 + gw] = delta_n * g[:, :gw]
    return vol


def _voxel_centres(shape, n_slices, pixel_size_um, slice_spacing_um):
    h, w = shape
    z = (np.arange(n_slices) + 0.5) * slice_spacing_um
    y = (np.arange(h) - h // 2) * pixel_size_um
    x = (np.arange(w) - w // 2) * pixel_size_um
    return z[:, None, None], y[None, :, None], x[None, None, :]


def _soft_ellipsoid(z, y, x, centre, semi_axes_um, angle_rad, edge_um):
    """Occupancy in [0, 1] of an ellipsoid rotated by ``angle_rad`` about z, with an edge ``edge_um`` wide."""
    cz, cy, cx = centre
    a, b, c = semi_axes_um
    ca, sa = np.cos(angle_rad), np.sin(angle_rad)
    u = (x - cx) * ca + (y - cy) * sa
    v = -(x - cx) * sa + (y - cy) * ca
    s = np.sqrt((u / a) ** 2 + (v / b) ** 2 + ((z - cz) / c) ** 2)
    return np.clip((1.0 - s) * min(a, b, c) / edge_um + 0.5, 0.0, 1.0)


def bead_phantom(
    shape: tuple[int, int],
    n_slices: int,
    pixel_size_um: float,
    slice_spacing_um: float,
    *,
    n_beads: int = 12,
    radius_um: tuple[float, float] = (1.0, 3.0),
    delta_n: float = 0.03,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Random spheres (radius uniform in ``radius_um``, µm) inside the volume, soft edges one pixel wide."""
    h, w = _check_shape(shape, n_slices)
    rng = np.random.default_rng(rng)
    z, y, x = _voxel_centres((h, w), n_slices, pixel_size_um, slice_spacing_um)
    thickness = n_slices * slice_spacing_um
    vol = np.zeros((n_slices, h, w), dtype=np.float64)
    for _ in range(int(n_beads)):
        r = rng.uniform(*radius_um)
        cz = rng.uniform(min(r, thickness / 2), max(thickness - r, thickness / 2))
        cy = rng.uniform(-(h // 2) * pixel_size_um + r, (h - h // 2) * pixel_size_um - r)
        cx = rng.uniform(-(w // 2) * pixel_size_um + r, (w - w // 2) * pixel_size_um - r)
        occ = _soft_ellipsoid(z, y, x, (cz, cy, cx), (r, r, r), 0.0, pixel_size_um)
        vol = np.maximum(vol, delta_n * occ)
    return vol.astype(np.float32)


def cell_phantom(
    shape: tuple[int, int],
    n_slices: int,
    pixel_size_um: float,
    slice_spacing_um: float,
    *,
    n_cells: int = 6,
    delta_n_cytoplasm: float = 0.02,
    delta_n_nucleus: float = 0.015,
    delta_n_droplet: float = 0.04,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Cell-like flattened ellipsoids on the bottom of the volume, each with a nucleus and a few lipid droplets.

    Cytoplasm Δn ``delta_n_cytoplasm``; the nucleus adds ``delta_n_nucleus``; droplets (0.4–0.8 µm) add
    ``delta_n_droplet``. Cells may overlap (the larger contrast wins).
    """
    h, w = _check_shape(shape, n_slices)
    rng = np.random.default_rng(rng)
    z, y, x = _voxel_centres((h, w), n_slices, pixel_size_um, slice_spacing_um)
    thickness = n_slices * slice_spacing_um
    half_h, half_w = (h // 2) * pixel_size_um, (w // 2) * pixel_size_um
    vol = np.zeros((n_slices, h, w), dtype=np.float64)
    edge = pixel_size_um
    for _ in range(int(n_cells)):
        a = rng.uniform(0.15, 0.3) * min(half_h, half_w) * 2 / 2
        b = a * rng.uniform(0.5, 0.9)
        c = min(rng.uniform(2.0, 5.0), thickness / 2)
        cz = c
        cy, cx = rng.uniform(-half_h + b, half_h - b), rng.uniform(-half_w + b, half_w - b)
        ang = rng.uniform(0, np.pi)
        cell = delta_n_cytoplasm * _soft_ellipsoid(z, y, x, (cz, cy, cx), (a, b, c), ang, edge)
        off = rng.uniform(-0.2, 0.2, 2) * np.array([a, b])
        nucleus = _soft_ellipsoid(z, y, x, (cz, cy + off[0], cx + off[1]), (0.4 * a, 0.45 * b, 0.7 * c), ang, edge)
        cell = cell + delta_n_nucleus * nucleus
        for _ in range(3):
            rd = rng.uniform(0.4, 0.8)
            t, rr = rng.uniform(0, 2 * np.pi), rng.uniform(0.55, 0.8)
            dy, dx_ = rr * a * np.sin(t), rr * b * np.cos(t)
            cell = np.maximum(cell, delta_n_droplet * _soft_ellipsoid(z, y, x, (cz, cy + dy, cx + dx_), (rd, rd, rd), 0, edge))
        vol = np.maximum(vol, cell)
    return vol.astype(np.float32)


def fibre_phantom(
    shape: tuple[int, int],
    n_slices: int,
    pixel_size_um: float,
    slice_spacing_um: float,
    *,
    n_fibres: int = 10,
    radius_um: tuple[float, float] = (0.5, 1.2),
    length_um: tuple[float, float] = (8.0, 20.0),
    max_tilt_deg: float = 30.0,
    delta_n: float = 0.03,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Random fibres: capsules (a segment of length ``length_um`` with round ends, radius ``radius_um``, µm) at random
    azimuths, tilted up to ``max_tilt_deg`` out of the lateral plane, so that in a thick slab each crosses several
    slices (elongated objects the missing cone stretches along z); Δn ``delta_n`` × 0.6–1, soft edges one pixel wide,
    the larger Δn where fibres cross."""
    h, w = _check_shape(shape, n_slices)
    rng = np.random.default_rng(rng)
    z, y, x = _voxel_centres((h, w), n_slices, pixel_size_um, slice_spacing_um)
    thickness = n_slices * slice_spacing_um
    half_h, half_w = (h // 2) * pixel_size_um, (w // 2) * pixel_size_um
    vol = np.zeros((n_slices, h, w), dtype=np.float64)
    for _ in range(int(n_fibres)):
        r, length = rng.uniform(*radius_um), rng.uniform(*length_um)
        centre = np.array([rng.uniform(min(r, thickness / 2), max(thickness - r, thickness / 2)),
                           rng.uniform(-half_h + r, half_h - r), rng.uniform(-half_w + r, half_w - r)])
        azimuth, tilt = rng.uniform(0, np.pi), np.deg2rad(rng.uniform(-max_tilt_deg, max_tilt_deg))
        d = np.array([np.sin(tilt), np.cos(tilt) * np.sin(azimuth), np.cos(tilt) * np.cos(azimuth)])  # (z, y, x)
        a = centre - 0.5 * length * d
        pz, py, px = z - a[0], y - a[1], x - a[2]
        t = np.clip((pz * d[0] + py * d[1] + px * d[2]) / length, 0.0, 1.0)
        dist = np.sqrt((pz - t * length * d[0]) ** 2 + (py - t * length * d[1]) ** 2 + (px - t * length * d[2]) ** 2)
        occ = np.clip((r - dist) / pixel_size_um + 0.5, 0.0, 1.0)
        vol = np.maximum(vol, delta_n * rng.uniform(0.6, 1.0) * occ)
    return vol.astype(np.float32)


#: Scene names accepted by ``fdt simulate``.
SCENES = ("letters", "beads", "cells", "fibres")
