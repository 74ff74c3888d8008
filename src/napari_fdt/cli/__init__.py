"""The ``fdt`` command line: ``simulate``, ``info``, ``plan``, ``forward`` and ``reconstruct``; one core shared with the API and napari
(the parser: :mod:`napari_fdt.cli.parser`).

Errors a user can cause print one line naming the field and the fix, and exit with status 2
(no traceback). Geometry warnings print as ``warning: …`` lines before any long computation.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from napari_fdt.cli.parser import build_parser
from napari_fdt.cli.progress import LONG_CPU_RUN_S, _progress_bar, _show_progress, _warn_about_a_long_cpu_run
from napari_fdt.errors import FDTInputError, FDTWarning

__all__ = ["main", "build_parser", "LONG_CPU_RUN_S"]


def _optics_from_args(args: argparse.Namespace):
    from napari_fdt.physics.optics import OPTICS_FIELDS, Optics

    return Optics(**{name: getattr(args, name) for name in OPTICS_FIELDS})


#: Host bytes per image pixel that ``fdt forward`` and ``fdt simulate`` hold besides the model: the images, the
#: predictions and their float64 working copies (gain fit, residuals; noise).
_HOST_BYTES_PER_IMAGE_PIXEL = 40


def _check_forward_memory(plan, n_slices: int, batch: int, n_images: int, device: str, *, extra_host_bytes: int = 0,
                          batch_fix: str | None = "lower --batch-size to {fits}", image_field: str = "images",
                          image_fix: str = "crop or bin the images, use fewer slices, or a device with more memory") -> int:
    """Refuse, before anything is allocated, a forward run that cannot fit; return the batch to use.

    The model's peak is :func:`napari_fdt.model.memory.forward_bytes`; on the host the results take
    :data:`_HOST_BYTES_PER_IMAGE_PIXEL` per image pixel (shared with the model when the device is the CPU).
    With ``batch_fix`` None the batch is lowered to what fits instead of refusing it.
    """
    import torch

    from napari_fdt.device import available_bytes, resolve_device
    from napari_fdt.model.memory import forward_bytes

    def size(n: float) -> str:
        return f"{n / 2.0**30:.1f} GiB" if abs(n) >= 2.0**30 else f"{n / 2.0**20:.0f} MiB"

    dev = resolve_device(device)
    h, w = plan.image_shape
    host = _HOST_BYTES_PER_IMAGE_PIXEL * n_images * h * w + int(extra_host_bytes)
    free_host = available_bytes(torch.device("cpu"))
    if free_host is not None and host > 0.9 * free_host:
        raise FDTInputError(image_field, f"{n_images} images of {h}x{w} px need about {size(host)} of memory "
                            f"for the results; {size(free_host)} are free", image_fix)
    free = available_bytes(dev)
    batch = max(1, min(int(batch), n_images))
    if free is None:
        return batch
    if dev.type == "cpu":
        free -= host
    hp, wp = plan.padded_shape
    if forward_bytes(plan.padded_shape, n_slices, batch) <= 0.9 * free:
        return batch
    fits = max((b for b in range(1, batch) if forward_bytes(plan.padded_shape, n_slices, b) <= 0.9 * free), default=0)
    if fits and batch_fix is None:
        return fits
    what = f"{hp}x{wp} window, {n_slices} slices; {size(max(free, 0))} are free on {dev}"
    if fits:
        need = forward_bytes(plan.padded_shape, n_slices, batch)
        raise FDTInputError("batch_size", f"a batch of {batch} images needs about {size(need)} ({what})",
                            batch_fix.format(fits=fits))
    need = forward_bytes(plan.padded_shape, n_slices, 1)
    raise FDTInputError(image_field, f"one image of {h}x{w} px needs about {size(need)} ({what})", image_fix)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from napari_fdt.data.io import write_acquisition, write_json_atomic, write_volume_tiff
    from napari_fdt.physics.aberrations import parse_aberrations
    from napari_fdt.sim.simulate import make_scene, simulate, source_grid

    optics = _optics_from_args(args)
    out = Path(args.out_dir)
    if out.exists() and not args.overwrite:
        raise FDTInputError("out_dir", f"{out} exists", "choose another folder or pass --overwrite")
    shape = tuple(args.shape)
    fov = min(shape) * optics.pixel_size_um
    span = 0.8 * fov if args.span_um is None else args.span_um
    sources = source_grid(args.sources, span, args.depth_um)
    from napari_fdt.physics.grid import MAX_PADDED_SIDE, plan_for_sources

    if min(shape) < 8 or max(shape) > MAX_PADDED_SIDE - 2:
        raise FDTInputError("shape", f"{shape[0]}x{shape[1]} px is outside 8 … {MAX_PADDED_SIDE - 2} px per side",
                            "give --shape H W within that range")

    plan = plan_for_sources(optics, shape, sources, warn=False)  # simulate() plans it again, with the warnings
    batch = _check_forward_memory(plan, optics.n_slices, 16, len(sources), args.device, batch_fix=None, image_field="shape",
                                  extra_host_bytes=8 * optics.n_slices * shape[0] * shape[1],
                                  image_fix="use a smaller --shape or fewer --n-slices, or a device with more memory")
    delta_n = make_scene(args.scene, shape, optics, delta_n=args.delta_n, text=args.text,
                         letter_height_px=args.letter_height_px, rng=args.seed)
    t0 = time.perf_counter()
    sim = simulate(delta_n, optics, sources, photons=args.photons, read_noise=args.read_noise,
                   brightness_spread=args.brightness_spread, jitter_xy_um=args.jitter_um, jitter_depth_um=args.jitter_um,
                   noise=not args.no_noise, seed=args.seed, device=args.device, uint16=args.uint16,
                   bandwidth_um=args.bandwidth_um, n_wavelengths=args.n_wavelengths, batch_size=batch,
                   pixel_integration=args.pixel_integration, pupil_edge=args.pupil_edge,
                   aberrations=parse_aberrations(args.aberrations),
                   sub_slices=args.sub_slices if args.sub_slices is not None else (4 if args.forward_accuracy == "high" else 1),
                   field_oversampling=(args.field_oversampling if args.field_oversampling is not None
                                       else (2 if args.forward_accuracy == "high" else 1)))
    seconds = time.perf_counter() - t0
    sim.acquisition.extra["simulated"].update(scene=args.scene, text=args.text if args.scene == "letters" else None)
    write_acquisition(sim.acquisition, out, overwrite=args.overwrite)
    write_volume_tiff(out / "ground_truth_ri.tif", sim.ri,
                      (optics.slice_spacing_um, optics.pixel_size_um, optics.pixel_size_um), overwrite=True)
    write_json_atomic(out / "ground_truth_sources_um.json", sim.truth_metadata(), overwrite=True)
    hp, wp = sim.plan.padded_shape
    spectral = ""
    if len(sim.settings["emission_wavelengths_um"]) > 1:
        spectral = (f"; emission FWHM {args.bandwidth_um * 1000:g} nm in {len(sim.settings['emission_wavelengths_um'])} wavelengths, "
                    f"coherence length {sim.settings['coherence_length_um']:.1f} µm")
    lowered = f"; {batch} images at a time (memory)" if batch < min(16, len(sources)) else ""
    print(f"wrote {out}: {sim.acquisition.n_images} images of {shape[0]}x{shape[1]} px, {optics.n_slices} slices; "
          f"window {hp}x{wp} px{spectral}{lowered}; {seconds:.1f} s")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from napari_fdt.data.io import read_acquisition
    from napari_fdt.physics.grid import plan_for_sources
    from napari_fdt.recon.problem.stages import thick_slices

    acq = read_acquisition(args.acquisition)
    o = acq.optics
    h, w = acq.image_shape
    print(f"{args.acquisition}: {acq.n_images} images of {h}x{w} px ({acq.images.dtype}), "
          f"field of view {h * o.pixel_size_um:.1f} x {w * o.pixel_size_um:.1f} µm")
    print(f"optics: λ {o.wavelength_um:g} µm, n_b {o.n_background:g}, NA {o.na:g}, pixel {o.pixel_size_um:g} µm, "
          f"{o.n_slices} slices x {o.slice_spacing_um:g} µm = {o.thickness_um:g} µm, image plane {o.image_plane_um:g} µm below the top")
    ratio = o.slice_spacing_um / o.depth_of_field_um
    print(f"slices: {ratio:.2f} of the depth of field ({o.depth_of_field_um:.2f} µm); a thin screen per slice misses the "
          "diffraction inside a slice, an image error growing as (slice/depth of field)^2 (1-7 % on the suite's scenes at "
          "0.84; docs/physics.md, \"Sub-slices\")"
          + (": the default --sub-slices auto tries 2 screens per slice in the finest stage and keeps them where the "
             "held-out images show it" if thick_slices(o) else ": thin screens (--sub-slices auto does not try more)"))
    nyquist, medium = 0.5 / o.pixel_size_um, o.n_background / o.wavelength_um
    if nyquist < medium:
        print(f"field grid: the camera's pixels hold waves up to {nyquist:.2f} cycles/µm of the {medium:.2f} the medium "
              "carries; what the sample scatters above is aliased (camera-grid images 1.4-4.1 % off on the suite's "
              "phantoms at 0.33 µm, NA 0.8; docs/physics.md, \"A finer field grid\"): --field-oversampling 2 propagates it "
              "at about 4x the finest stage's cost; --field-oversampling auto tries it and keeps it where the held-out images show it")
    if acq.sources_um is None:
        print("sources: none given (the solver fits them)")
        return 0
    s = acq.sources_um
    print(f"sources: x {s[:, 0].min():.1f}..{s[:, 0].max():.1f} µm, y {s[:, 1].min():.1f}..{s[:, 1].max():.1f} µm, "
          f"depth {s[:, 2].min():.1f}..{s[:, 2].max():.1f} µm")
    plan = plan_for_sources(o, acq.image_shape, s)
    hp, wp = plan.padded_shape
    print(f"forward window: {hp}x{wp} px ({plan.padding_factor:.2f}x the image area), light-cone margin {plan.margin_um:.1f} µm, "
          f"band limit {plan.f_lo_per_um:.3f}..{plan.f_hi_per_um:.3f} cycles/µm")
    from napari_fdt.model.split_field import split_plan
    from napari_fdt.recon.problem.stages import SPLIT_MAX_FRACTION, split_window_fraction

    sh, sw = split_plan(plan, o).padded_shape
    fraction = split_window_fraction(plan, o)
    use = "the solver's default on CPU" if fraction <= SPLIT_MAX_FRACTION else "not the default: the light cone fills the window"
    print(f"split-field window: {sh}x{sw} px ({fraction:.0%} of the forward window's pixels): the sources' field exact, what "
          f"the sample adds on the image and its light cone ({use}; field_window, docs/decisions/split-field.md)")
    return 0


def _cmd_plan(args: argparse.Namespace) -> int:
    import json

    from napari_fdt.cli.family import family_json, family_on, family_summary, planned_config
    from napari_fdt.data.io import read_acquisition
    from napari_fdt.device import resolve_device
    from napari_fdt.recon.loop.plan import plan_for
    from napari_fdt.recon.problem.preflight import finest_stage_bytes
    from napari_fdt.recon.settings.config import resolve_stage_lengths

    config = _config_from_args(args)
    acq = read_acquisition(args.acquisition)
    device = resolve_device(args.device)
    family = family_on(config, args)
    plan, src = plan_for(acq, planned_config(config, family), device.type)
    k = config.n_wavelengths if config.coherence in ("spectral", "mask+spectral") else 1
    peak, _, _, _ = finest_stage_bytes(acq, resolve_stage_lengths(config, acq.n_images), src, k, device.type)
    if args.json:
        print(json.dumps({**plan.to_dict(), "peak_memory_bytes": int(peak), **family_json(family, plan)}))
        return 0
    print(family_summary(family, plan))
    held = "the finest stage's batch" + (" and the images" if device.type != "cpu" else "; the images are read from the file")
    print(f"peak memory: about {peak / 2.0**30:.2f} GiB on {device} ({held})")
    return 0


def _cmd_forward(args: argparse.Namespace) -> int:
    import torch

    from napari_fdt.data.io import read_acquisition, read_volume_tiff, write_stack_tiff
    from napari_fdt.model.forward import MultiSliceModel
    from napari_fdt.model.gain import least_squares_gain
    from napari_fdt.model.render import render_images
    from napari_fdt.physics.grid import plan_for_sources

    acq = read_acquisition(args.acquisition)
    o = acq.optics
    if args.out is not None and Path(args.out).exists() and not args.overwrite:
        raise FDTInputError("out", f"{args.out} exists", "choose another file or pass --overwrite")
    if args.batch_size < 1:
        raise FDTInputError("batch_size", f"must be >= 1, got {args.batch_size}", "use e.g. 16")
    if acq.sources_um is None:
        raise FDTInputError("sources_um", "the acquisition has no source positions", "add sources_um to acquisition.json")
    plan = plan_for_sources(o, acq.image_shape, acq.sources_um)
    h, w = acq.image_shape
    _check_forward_memory(plan, o.n_slices, args.batch_size, acq.n_images, args.device,
                          extra_host_bytes=12 * o.n_slices * h * w)  # the RI volume and its float32 copies
    ri, _ = read_volume_tiff(args.ri)
    expected = (o.n_slices, *acq.image_shape)
    if ri.shape != expected:
        raise FDTInputError("ri", f"volume shape {ri.shape} does not match the acquisition's {expected}",
                            "give a volume of (n_slices, H, W) on the acquisition's grid")
    model = MultiSliceModel(o, plan, device=args.device)
    t0 = time.perf_counter()
    pred = render_images(model, ri.astype(np.float32) - np.float32(o.n_background), acq.sources_um, batch_size=args.batch_size)
    seconds = time.perf_counter() - t0
    meas = acq.images_float32().astype(np.float64)
    p = pred.astype(np.float64)
    gain = least_squares_gain(torch.from_numpy(p), torch.from_numpy(meas)).numpy()  # brightness is unknown per fluorophore
    fit = p * gain[:, None, None]
    rel = np.linalg.norm((fit - meas).reshape(len(meas), -1), axis=1) / np.maximum(
        np.linalg.norm(meas.reshape(len(meas), -1), axis=1), 1e-30)
    total = float(np.linalg.norm(fit - meas) / np.linalg.norm(meas))
    n_img = acq.n_images
    print(f"forward: {n_img} images x {o.n_slices} slices in {seconds:.2f} s on {model.device} "
          f"({n_img * o.n_slices / seconds:.0f} image-slices/s), window {model.plan.padded_shape[0]}x{model.plan.padded_shape[1]}")
    print(f"relative residual after a per-image gain: {total:.4f} overall; per image median {np.median(rel):.4f}, "
          f"worst {rel.max():.4f} (image {int(rel.argmax())})")
    if args.out is not None:
        write_stack_tiff(args.out, fit.astype(np.float32), o.pixel_size_um, overwrite=args.overwrite)
        print(f"wrote {args.out}")
    return 0


def _config_from_args(args: argparse.Namespace):
    """The settings of ``fdt reconstruct``: the ``--config`` file (or report's config), then each flag given."""
    from napari_fdt.recon.settings.command import config_from_file
    from napari_fdt.recon.settings.config import SolverConfig
    from napari_fdt.schema import schema_fields

    config = config_from_file(args.config) if args.config is not None else SolverConfig()
    overrides = {name: getattr(args, name) for name in schema_fields(SolverConfig) if getattr(args, name, None) is not None}
    if overrides:
        config = dataclasses.replace(config, **overrides)  # validated again
    return config


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    import json

    from napari_fdt.data.io import check_report_free, read_acquisition, read_volume_tiff, report_path
    from napari_fdt.recon.problem import distributed
    from napari_fdt.recon.settings.command import read_report

    config = _config_from_args(args)
    # Under torchrun every rank runs this; everything up to the process group is checked on all ranks alike,
    # and only rank 0 writes or prints progress.
    _, rank, _, _ = distributed.world_from_env()
    if rank != 0:
        warnings.simplefilter("ignore", FDTWarning)  # rank 0 prints them once
    if args.save_config is not None:
        if rank == 0:
            config.save(args.save_config)
            print(f"wrote {args.save_config}")
        return 0
    if args.acquisition is None:
        report = read_report(args.config) if args.config is not None else None
        if report is None or not isinstance(report.get("acquisition"), str):
            raise FDTInputError("acquisition", "is missing", "give the acquisition folder (or --config a report that names it)")
        args.acquisition = Path(report["acquisition"])
    acq = read_acquisition(args.acquisition)
    out = Path(args.out)
    json_out = report_path(out)
    protected = {Path(args.acquisition).resolve() / "images.tif", Path(args.acquisition).resolve() / "acquisition.json",
                 Path(args.acquisition).resolve()}
    for given in (args.truth, args.config):
        if given is not None:
            protected.add(Path(given).resolve())
    if out.resolve() in protected or json_out.resolve() in protected:
        raise FDTInputError("out", f"{out} (or its report {json_out.name}) would overwrite an input", "write the result somewhere else")
    outputs = [out, json_out]
    if config.error_bounds:
        from napari_fdt.cli.bounds import check_bounds_request

        outputs.append(check_bounds_request(config, out, protected, distributed.world_from_env()[0]))
    for p in outputs:
        if p.exists() and not args.overwrite:
            raise FDTInputError("out", f"{p} exists", "choose another --out or pass --overwrite")
    check_report_free(out)  # RI.tif and RI.ome.tif share RI.json: refuse before the run, not after it
    if str(out).lower().endswith(".zarr"):
        from napari_fdt.data.ome_zarr import _zarr

        _zarr()  # refuse now, not after the run, when zarr is missing
    truth = truth_src = None
    if args.truth is not None:
        truth, _ = read_volume_tiff(args.truth)
        expected = (acq.optics.n_slices, *acq.image_shape)
        if truth.shape != expected:
            raise FDTInputError("truth", f"volume shape {truth.shape} does not match the acquisition's {expected}",
                                "give the ground truth of this acquisition")
        side = Path(args.truth).with_name("ground_truth_sources_um.json")
        if side.exists():
            truth_src = np.asarray(json.loads(side.read_text())["sources_um"], dtype=np.float64)
    from napari_fdt.cli.family import check_family_request, family_on, run_family_and_write

    run = _run_and_write
    if family_on(config, args, distributed_launch=distributed.world_from_env()[0] > 1):  # (cli/family.py: a run per TV weight)
        check_family_request(config, args, out)
        run = run_family_and_write
    group = distributed.setup(args.device, args.dist_backend)
    completed = False
    try:
        code = run(args, config, acq, out, truth, truth_src, group)
        completed = True
        return code
    finally:
        distributed.teardown(group, completed=completed)


def _run_and_write(args, config, acq, out: Path, truth, truth_src, group) -> int:
    from napari_fdt.cli.resolution import add_resolution_and_write
    from napari_fdt.data.io import report_path
    from napari_fdt.recon.run.report import describe_parts, describe_plan, write_result
    from napari_fdt.recon.run.session import bounds_due, finish_run, open_run, resolution_due

    device, json_out = args.device if group is None else group.device, report_path(out)
    rec = open_run(acq, config, device=device, resume=args.resume, group=group)
    writer = group is None or group.is_writer
    cancelled = False
    if writer:  # what the run will do and cost, before it starts (also with --quiet: a batch log shows it)
        print(rec.plan.summary(), file=sys.stderr)
        _warn_about_a_long_cpu_run(rec.plan, rec.device.type)
    bar = _progress_bar(rec.plan.iterations, disable=args.quiet or not writer)
    snapshots = rec.run(checkpoint_dir=args.checkpoint_dir)
    try:
        for snap in snapshots:
            _show_progress(bar, snap)
    except KeyboardInterrupt:
        snapshots.close()  # interrupted between two snapshots (maybe during the TV trials): the last complete stage stays
        cancelled = True
        bar.close()
        if not writer:
            return 130
        if rec.completed_stages == 0:
            print("interrupted before the first stage completed: nothing written", file=sys.stderr)
            return 130
        print(f"interrupted: writing the last complete stage ({rec.completed_stages}/{len(rec.config.stages)})", file=sys.stderr)
    bar.close()
    if not writer:
        return 0
    report = finish_run(rec, cancelled, output=str(out), acquisition_path=str(args.acquisition), truth_ri=truth,
                        truth_sources_um=truth_src)
    write_result(rec, out, report, overwrite=args.overwrite)
    st = ", ".join(f"x{r['factor']}: {r.get('stopped_at') or r['iterations']} it, {r['seconds_per_iteration']:.3f} s/it" for r in report["stages"])
    print(f"wrote {out} and {json_out}: {report['seconds_total']:.1f} s on {rec.device} ({st})")
    print(describe_plan(report["plan"]))
    lengths = report.get("stage_lengths")
    if lengths and lengths["iterations"] != lengths["requested_iterations"]:
        print(f"finest stage lengthened to {lengths['iterations'][-1]} iterations (asked {lengths['requested_iterations'][-1]}): "
              f"{lengths['passes'][-1]:.0f} passes over the {lengths['n_images']} images, so that every source is fitted "
              f"at least {lengths['final_stage_min_passes']:g} times (final_stage_min_passes)")
    fit = report.get("image_fit")
    if fit:
        print(f"image fit: relative error {fit['image_relative_error']:.4f}, PSNR {fit['image_psnr']:.1f} dB, SSIM {fit['image_ssim']:.3f}")
    reg = report.get("regularisation", {})
    chosen = reg.get("chosen")
    if chosen and chosen.get("trials"):
        tried = ", ".join(f"{t['tv_xy_weight']:g}: {t['validation_error']:.4f}" for t in chosen["trials"])
        print(f"TV weights chosen by the validation error: τ_xy {chosen['tv_xy_weight']:g}, τ_z {chosen['tv_z_weight']:g} "
              f"(stage {chosen['stage'] + 1}, {chosen['probe_iterations']} iterations per candidate, {chosen['seconds']:.1f} s; τ_xy: error {tried})")
    elif chosen:
        print(f"TV weights: τ_xy {chosen['tv_xy_weight']:g}, τ_z {chosen['tv_z_weight']:g} ({chosen['reason']})")
    if report.get("model_parts"):
        print(describe_parts(report["model_parts"]))
    val = report.get("validation")
    if val:
        print(f"validation: relative error {val['error']:.4f} on {val['n_images']} held-out images (the image fit's counterpart "
              f"on images the volume was not fitted to)")
    m = report.get("metrics", {})
    if "relative_delta_n_error" in m:
        print(f"against the truth: relative Δn error {m['relative_delta_n_error']:.3f}, RI RMSE {m['ri_rmse']:.2e}, "
              f"normalised PSNR {m['paper_normalised']['psnr']:.1f} dB, SSIM {m['paper_normalised']['ssim']:.3f}")
    if "sources" in m:
        print(f"sources: lateral RMS error {m['sources']['lateral_rms_um']:.3f} µm (initial {m['sources_initial']['lateral_rms_um']:.3f} µm)")
    if resolution_due(rec, cancelled):
        report = add_resolution_and_write(rec, report, json_out, args.quiet)
    if bounds_due(rec, cancelled):
        from napari_fdt.cli.bounds import add_bounds_and_write

        add_bounds_and_write(rec, report, out, json_out, args.quiet, args.overwrite)
    return 130 if cancelled else 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``fdt``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from napari_fdt._version import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 2

    def show_warning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, FDTWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            print(warnings.formatwarning(message, category, filename, lineno, line), file=sys.stderr, end="")

    warnings.showwarning = show_warning
    commands = {"simulate": _cmd_simulate, "info": _cmd_info, "plan": _cmd_plan, "forward": _cmd_forward,
                "reconstruct": _cmd_reconstruct}
    try:
        return commands[args.command](args)
    except FDTInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: no output was left half-written", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
