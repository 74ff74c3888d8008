"""Can a coarse stage's multi-slice model cut the field's band? Measured on the demo optics (issue 16, item 1a).

    OMP_NUM_THREADS=1 python -m benchmarks run coarse_field_band        # → benchmarks/results/coarse_field_band.json

A stage of factor f compares block-averaged (f×f) images. A multi-slice model on a field grid of f·dx would hold
field frequencies below 1/(2·f·dx) only, while the pupil passes up to NA/λ. Since the intensity is |E|², its low
frequencies (and the block averages) are sums over *all* pairs of field frequencies inside the pupil, so a band cut
of the field changes them too. This script measures by how much: the exact camera field of the multi-slice model
(demo optics: λ 0.6 µm, NA 0.65, pixel 0.33 µm, 14 slices 1.5 µm apart, letters Δn 0.03, sources 50 µm deep) is
cut to ``|f| ≤ c·NA/λ`` for several c, and the block-averaged intensities at f = 4 and 2 are compared with those of
the uncut field (relative L2 error over the images), with and without a least-squares gain per image (the solver
fits one), and only on the pixels that the cut pupil still sees from each source with a margin (sin θ ≤ 0.9·c·NA/n_b,
as the envelope model's ``coverage``): what a coarse model with a cut band could be compared on. For scale, the
same comparison for the envelope model of the stage (``build_stage(coarse_model="envelope")``, the RI block-averaged
to the stage grid) inside its coverage. c = 1/(2·f·dx)/(NA/λ) is what a field grid of f·dx could hold.
"""

from __future__ import annotations

from pathlib import Path

import torch

from benchmarks._results import RESULTS, write_document
from napari_fdt import Optics, source_grid
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.propagation import pupil
from napari_fdt.recon.stages import block_average
from napari_fdt.sim.simulate import make_scene

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=14, slice_spacing_um=1.5,
               image_plane_um=10.5)
    side = 128
    dn = make_scene("letters", (side, side), o, delta_n=0.03, text="FD", letter_height_px=40)
    src = source_grid(3, 24.0, 50.0)
    model = MultiSliceModel(o, plan_for_sources(o, (side, side), src), device="cpu", dtype=torch.float64)
    k = model.kernels()
    with torch.no_grad():
        spec, _ = model._camera_spectra(torch.as_tensor(dn, dtype=torch.float64), torch.as_tensor(src), k)
        f = torch.sqrt(k.fy**2 + k.fx**2)
        cutoff = o.na / o.wavelength_um
        exact = model.crop(torch.fft.ifft2(spec)).abs().square()
        # sine of the angle under which each source sees each image pixel (camera focal plane)
        oy, ox = model.plan.offset
        ys = model._window_coordinates(oy, oy + side, 0, 1.0, o.pixel_size_um)
        xs = model._window_coordinates(ox, ox + side, 1, 1.0, o.pixel_size_um)
        s_t = torch.as_tensor(src)
        h_cam = s_t[:, 2] + o.thickness_um - o.image_plane_um
        r2 = (ys[None, :, None] - s_t[:, 1, None, None]) ** 2 + (xs[None, None, :] - s_t[:, 0, None, None]) ** 2
        sine = torch.sqrt(r2 / (r2 + h_cam[:, None, None] ** 2))
        rows = []
        for factor in (4, 2):
            ref = block_average(exact, factor)
            c_grid = 1.0 / (2 * factor * o.pixel_size_um) / cutoff
            for c, edge in [(c, 0.0) for c in sorted({round(c_grid, 3), 0.5, 0.75, 0.9, 0.95, 0.99})] + [(round(c_grid, 3) / 1.2, 0.2)]:
                # edge > 0: a raised-cosine cut reaching zero at (1 + edge)·c·NA/λ (the grid's limit for the last row)
                window = pupil(f * f, c * o.na, o.wavelength_um, edge)
                cut = model.crop(torch.fft.ifft2(spec * window)).abs().square()
                img = block_average(cut, factor)
                err = float((img - ref).norm() / ref.norm())
                gain = (img * ref).sum((-2, -1), keepdim=True) / (img * img).sum((-2, -1), keepdim=True)
                err_gain = float((gain * img - ref).norm() / ref.norm())
                # only where the cut pupil still sees the source with margin (as the envelope model's coverage)
                inside = block_average((sine <= 0.9 * c * o.na / o.n_background).double(), factor) == 1
                err_inside = float(((img - ref) * inside).norm() / (ref * inside).norm()) if inside.any() else float("nan")
                rows.append({"factor": factor, "cut_fraction_of_na": c, "soft_edge": edge, "grid_holds": abs(c - round(c_grid, 3)) < 1e-9,
                             "relative_error": err, "relative_error_after_gain": err_gain,
                             "relative_error_inside_covered": err_inside, "covered_fraction": float(inside.double().mean())})
                print(f"f={factor} cut at {c:5.3f}·NA/λ{' (the f·dx grid)' if rows[-1]['grid_holds'] else ''}"
                      f"{f' soft edge ±{edge}' if edge else ''}: "
                      f"error {err:.3f}, after a gain per image {err_gain:.3f}; inside the cut cone ({float(inside.double().mean()):.2f} "
                      f"of the pixels) {err_inside:.3f}", flush=True)
        # for scale: how much the object changes the block-averaged images
        empty = model.crop(torch.fft.ifft2(model._camera_spectra(torch.zeros_like(torch.as_tensor(dn, dtype=torch.float64)),
                                                                 torch.as_tensor(src), k)[0])).abs().square()
        signal = {fct: float((block_average(exact, fct) - block_average(empty, fct)).norm() / block_average(exact, fct).norm())
                  for fct in (4, 2)}
        print(f"object signal (block-averaged images with the object against without): {signal}")
        # for comparison: the envelope model of the stage (what coarse_model "envelope" runs), inside its coverage
        from napari_fdt.recon.stages import build_stage

        envelope = {}
        for fct in (4, 2):
            stage = build_stage(0, fct, 1, o, exact.float(), src, device=torch.device("cpu"), coarse_model="envelope")
            dn_stage = block_average(torch.as_tensor(dn, dtype=torch.float32), fct)
            pred = stage.model(dn_stage, stage.stage_sources(torch.as_tensor(src, dtype=torch.float32)))
            cov = stage.coverage
            ref = stage.images
            gain = (pred * ref * cov).sum((-2, -1), keepdim=True) / (pred * pred * cov).sum((-2, -1), keepdim=True)
            envelope[fct] = {"relative_error_inside_coverage": float(((pred - ref) * cov).norm() / (ref * cov).norm()),
                             "after_gain": float(((gain * pred - ref) * cov).norm() / (ref * cov).norm()),
                             "covered_fraction": float(cov.mean())}
            print(f"envelope model f={fct}: error inside its coverage ({envelope[fct]['covered_fraction']:.2f} of the pixels) "
                  f"{envelope[fct]['relative_error_inside_coverage']:.3f}, after a gain per image {envelope[fct]['after_gain']:.3f}", flush=True)
    out = write_document(RESULTS / "coarse_field_band.json", {"image": side, "sources": len(src), "object_signal": signal,
                                                              "envelope": envelope, "rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
