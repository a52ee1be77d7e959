"""`skyview demo` (simulate, solve two ways, solve a real photograph, open the viewer) and `skyview simulate`."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np

from skyview.cli.common import (
    ARCSEC,
    EXIT_NOT_SOLVED,
    EXIT_SOLVED,
    add_epoch,
    add_method,
    add_variant,
    float_arg,
    progress_line,
)
from skyview.cli.solve import against_truth, print_human
from skyview.core.errors import BadInput


def cmd_simulate(a) -> int:
    from skyview.core.attitude import R_from_radec_roll
    from skyview.core.camera import Camera
    from skyview.core.catalog import load_guide_catalog
    from skyview.detect.centroids import max_image_pixels
    from skyview.simulate.render import (
        IMAGE_SUFFIXES,
        JPEG_DEFAULT_QUALITY,
        SensorModel,
        is_jpeg_path,
        save_frame,
        save_sequence,
        simulate_image,
        simulate_sequence,
    )

    if not -90.0 <= a.dec <= 90.0:
        raise BadInput(f"declination {a.dec} deg is outside [-90, 90]")
    if a.seed < 0:
        raise BadInput(f"--seed {a.seed} must be a whole number >= 0")
    if a.frames < 1:
        raise BadInput(f"--frames {a.frames} must be at least 1")
    if a.width < 16 or (a.height is not None and a.height < 16):
        raise BadInput("--width and --height must be at least 16 pixels")
    if a.width * (a.height or a.width) > max_image_pixels():
        raise BadInput(f"a {a.width} x {a.height or a.width} image is more than the {max_image_pixels() / 1e6:.0f} MP "
                       f"skyview handles (SKYVIEW_MAX_PIXELS raises it)")
    if a.jpeg_quality is not None and not 1 <= a.jpeg_quality <= 100:
        raise BadInput(f"--jpeg-quality {a.jpeg_quality} must be in 1..100")
    if a.faint_extra_mag < 0:
        raise BadInput(f"--faint-extra-mag {a.faint_extra_mag} must be >= 0")
    if not 0.0 <= a.vignetting < 1.0:
        raise BadInput(f"--vignetting {a.vignetting} must be a fraction in [0, 1)")
    if not 0.0 <= a.sky_gradient <= 1.0:
        raise BadInput(f"--sky-gradient {a.sky_gradient} must be a fraction in [0, 1]")
    out = Path(a.out)
    if a.jpeg_quality is not None and out.suffix.lower() == ".png":
        out = out.with_suffix(".jpg")  # --jpeg-quality writes a JPEG
    jpeg_quality = a.jpeg_quality if a.jpeg_quality is not None else (
        JPEG_DEFAULT_QUALITY if is_jpeg_path(out) else None)
    camera = Camera.from_fov(a.fov_deg, a.width, a.height, k1=a.distortion[0], k2=a.distortion[1])
    sensor = SensorModel(bit_depth=a.bit_depth, **({"exposure_s": a.exposure_s} if a.exposure_s else {}))
    catalog = load_guide_catalog(epoch=a.epoch)
    R = R_from_radec_roll(np.radians(a.ra), np.radians(a.dec), np.radians(a.roll))
    kw = dict(seed=a.seed, mag_limit=a.mag_limit, n_false_stars=a.false_stars, n_dropped=a.dropped,
              position_noise_rad=a.noise_arcsec * ARCSEC)
    effects = dict(faint_extra_mag=a.faint_extra_mag, vignetting=a.vignetting, sky_gradient=a.sky_gradient,
                   sky_gradient_deg=a.sky_gradient_deg, jpeg_quality=jpeg_quality)
    kw.update({k: v for k, v in effects.items() if v})  # effects left off are not passed
    if a.frames > 1:
        # --out names a folder (frame_000.png ... and sequence.json in it), made when it is not there yet (its
        # parent must be); a path ending in .json or an image suffix writes <stem>_000.png ... and <stem>.json
        made = None
        if not out.exists() and not out.is_symlink() and out.suffix.lower() not in (*IMAGE_SUFFIXES, ".json"):
            if not out.parent.is_dir():
                raise BadInput(f"folder {out.parent} does not exist")
            out.mkdir()
            made = out
        seq = simulate_sequence(catalog, camera, R, a.frames, _turn(a), sensor, **kw)
        try:
            paths = save_sequence(seq, out, force=a.force)
        except BaseException:
            if made is not None:  # (the folder this run made, left empty by the failed write)
                with contextlib.suppress(OSError):
                    made.rmdir()
            raise
        print(f"wrote {len(seq.frames)} frames and {paths[-1]}")
        return EXIT_SOLVED
    frame = simulate_image(catalog, camera, R, sensor, **kw)
    img, js = save_frame(frame, out, force=a.force)
    n_faint = sum(1 for st in frame.truth["stars"] if st.get("faint"))
    print(f"wrote {img} ({camera.width}x{camera.height}, {len(frame.truth['stars'])} stars"
          + (f" of which {n_faint} fainter than Hp {a.mag_limit:g}" if a.faint_extra_mag else "")
          + f", {len(frame.truth['false_stars'])} false"
          + (f", JPEG quality {jpeg_quality}" if jpeg_quality is not None else "") + f") and truth {js}")
    return EXIT_SOLVED


def _turn(a):
    from skyview.simulate.render import turn_about_camera_axis

    axis = {"x": 0, "y": 1, "z": 2}[a.turn_axis]
    return turn_about_camera_axis(axis, np.radians(a.turn_deg))


def cmd_demo(a) -> int:
    from skyview.core.attitude import R_from_radec_roll
    from skyview.core.camera import Camera
    from skyview.core.catalog import REPO_ROOT, load_guide_catalog
    from skyview.simulate.render import SensorModel, simulate_image
    from skyview.solver.pipeline import MethodSolver, blind_solver

    t0 = time.perf_counter()
    catalog = load_guide_catalog()
    camera = Camera.from_fov(a.fov_deg, 1024)
    R = R_from_radec_roll(np.radians(a.ra), np.radians(a.dec), np.radians(a.roll))
    frame = simulate_image(catalog, camera, R, SensorModel(), seed=a.seed, mag_limit=6.0)
    print(f"1. simulated a {camera.width}x{camera.height} image, FOV {a.fov_deg:g} deg, pointing RA {a.ra:g} "
          f"Dec {a.dec:+g} roll {a.roll:g} deg: {len(frame.truth['stars'])} stars of Hp <= 6.0")

    def with_truth(result, R_true, truth=None) -> dict:
        out = result.to_dict()
        if result.R is not None:
            out["truth"] = against_truth(result, R_true, truth)
        return out

    solver = MethodSolver(camera, a.method, catalog=catalog, variant=a.variant)
    print(f"\n2. {a.method} ({a.variant}), told the exact FOV (database loaded in "
          f"{solver.setup_ms['database_load']:.0f} ms; a first run builds and caches it):")
    result = solver.solve_array(frame.image, measure_all=True)  # every detected star, as its recording draws them
    out = with_truth(result, R, frame.truth)
    print_human(out)
    if a.record:  # the demo's own recording: an earlier demo's is replaced
        from skyview.record.recording import record_solve

        info = record_solve(a.record, result, frame.image, catalog=result.catalog, truth=frame.truth, force=True,
                            meta={"command": "skyview demo", "seed": a.seed})
        print(f"  recorded every step in {info.path} ({info.bytes / 1e6:.2f} MB): skyview replay {info.path}")
    blind = blind_solver(catalog=catalog, progress=progress_line)
    print(f"\n3. the default pipeline, blind: no FOV given (the pattern database of the whole sky loaded in "
          f"{blind.setup_ms['database_load']:.0f} ms; a first run builds it once, ~15-20 s):")
    bres = blind.solve_array(frame.image)
    print_human(with_truth(bres, R, frame.truth))
    photos = REPO_ROOT / "tests" / "data" / "real-images"
    photo = None
    if (photos / "reference.json").exists():
        from skyview.detect.centroids import load_image

        ref = json.loads((photos / "reference.json").read_text())
        name = sorted(ref)[0]
        print(f"\n4. a real photograph, blind ({name}, {photos.relative_to(REPO_ROOT)}; its reference attitude "
              f"is cedar-solve's):")
        pres = blind.solve_array(load_image(photos / name))
        print_human(with_truth(pres, np.asarray(ref[name]["R"])))
        photo = photos / name
    print(f"\ntotal {1e3 * (time.perf_counter() - t0):.0f} ms. Next: skyview solve YOUR_PHOTO.jpg, skyview view")
    if a.json:
        print(json.dumps(out))
    code = EXIT_SOLVED if result.solved and bres.solved else EXIT_NOT_SOLVED
    if a.no_view or not (sys.stdin.isatty() and sys.stdout.isatty()):
        # headless (--no-view, a script, a pipe, a test): print and exit, never block
        print("(viewer not opened: --no-view or not a terminal; 'skyview view' opens it)")
        return code
    from skyview.viewer.app import serve
    from skyview.viewer.run import SceneConfig

    scene = SceneConfig(ra_deg=a.ra % 360.0, dec_deg=a.dec, roll_deg=a.roll, fov_deg=a.fov_deg, seed=a.seed)
    if photo is not None:  # the viewer opens on the real photograph, solved blind, in its place on the sky
        print(f"\n5. the viewer on the photograph ({photo.name}), solved blind: its catalog stars on its stars, "
              f"the fitted camera; the Steps tab tells how it was found. 'Back to the simulation' renders its sky, "
              f"where Method {a.method} steps through the papers' identification.")
        serve(image=str(photo), config=scene, method=None, say=lambda line: print(line, flush=True))
        return code
    print(f"\n5. the viewer on this solved scene ({a.method}, {a.variant}): step through how it was identified.")
    serve(config=scene, method=a.method, variant=a.variant, say=lambda line: print(line, flush=True))
    return code


def add_parsers(sub) -> None:
    d = sub.add_parser("demo", help="simulate a default sky (Orion), solve it and open the viewer on it",
                       description="Simulate a 1024 x 1024 image (Hp <= 6), solve it with one method at the "
                                   "exact FOV (saved step by step as demo.rrd) and with the default blind pipeline "
                                   "(no FOV), and solve one of the real photographs in tests/data/ blind; each "
                                   "compared with its truth. In a terminal it then opens the viewer on the solved "
                                   "scene (prints its URL; Ctrl-C stops it).")
    d.add_argument("--ra", type=float_arg, default=83.8, help="boresight right ascension, deg (default 83.8)")
    d.add_argument("--dec", type=float_arg, default=-5.4, help="boresight declination, deg (default -5.4)")
    d.add_argument("--roll", type=float_arg, default=30.0,
                   help="roll: image up from north towards east, deg (default 30)")
    d.add_argument("--fov-deg", type=float_arg, default=8.0, help="horizontal full field of view, deg (default 8)")
    d.add_argument("--seed", type=int, default=1, help="random seed of the image noise, an integer >= 0 (default 1)")
    add_method(d, "angle", "identification method: {methods} (default angle)")
    add_variant(d)
    d.add_argument("--json", action="store_true", help="also print the result as JSON")
    d.add_argument("--record", default="demo.rrd", metavar="PATH",
                   help="save the method's solve, step by step, as a Rerun recording (default demo.rrd in this "
                        "folder, replacing an earlier demo's; '' for none)")
    d.add_argument("--no-view", action="store_true",
                   help="do not open the viewer at the end (it opens only in a terminal: in a script or a pipe "
                        "the demo prints and exits)")
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("simulate", help="render a star-field image (PNG) and its truth sidecar (JSON)",
                       description="Render a star-field image at a given attitude (and a truth sidecar IMAGE.json); "
                                   "with --frames, a slew sequence with known turns (a folder with sequence.json).")
    s.add_argument("--ra", type=float_arg, required=True, help="boresight right ascension, deg")
    s.add_argument("--dec", type=float_arg, required=True, help="boresight declination, deg (-90 to 90)")
    s.add_argument("--roll", type=float_arg, default=0.0, help="image up from north towards east, deg (default 0)")
    s.add_argument("--fov-deg", type=float_arg, default=8.0, help="horizontal full field of view, deg (default 8)")
    s.add_argument("--width", type=int, default=1024, help="image width, pixels (default 1024)")
    s.add_argument("--height", type=int, default=None, help="image height, pixels (default: the width)")
    s.add_argument("--seed", type=int, default=0, help="random seed of the noise, an integer >= 0 (default 0)")
    s.add_argument("--mag-limit", type=float_arg, default=6.0,
                   help="render stars with Hp <= this, Hipparcos magnitude (default 6)")
    s.add_argument("--false-stars", type=int, default=0,
                   help="number of bright blobs that are not stars (debris) (default 0)")
    s.add_argument("--dropped", type=int, default=0, help="number of catalog stars left out of the image (default 0)")
    s.add_argument("--noise-arcsec", type=float_arg, default=0.0,
                   help="extra 1-sigma jitter of star directions, arcsec (default 0)")
    s.add_argument("--bit-depth", type=int, choices=(8, 16), default=8, help="bits per pixel: 8 or 16 (default 8)")
    s.add_argument("--exposure-s", type=float_arg, default=None, help="exposure time, seconds (default: the sensor's)")
    s.add_argument("--distortion", type=float_arg, nargs=2, default=(0.0, 0.0), metavar=("K1", "K2"),
                   help="OpenCV radial distortion coefficients k1 k2 (dimensionless, on normalised coordinates; "
                        "default 0 0)")
    add_epoch(s)
    s.add_argument("--frames", type=int, default=1, help="a slew sequence of this many frames (default 1)")
    s.add_argument("--turn-deg", type=float_arg, default=1.0,
                   help="turn between frames, deg (with --frames; default 1)")
    s.add_argument("--turn-axis", choices=("x", "y", "z"), default="y",
                   help="camera axis of the turn: x, y or z (default y)")
    s.add_argument("--faint-extra-mag", type=float_arg, default=0.0,
                   help="also render field stars this many magnitudes fainter than --mag-limit (to Hp 9 at most); "
                        "truth marks them faint")
    s.add_argument("--vignetting", type=float_arg, default=0.0,
                   help="fraction of light lost at the image corners, 0-1 (cos^4-shaped falloff)")
    s.add_argument("--sky-gradient", type=float_arg, default=0.0,
                   help="fraction by which the sky background changes across the frame, 0-1")
    s.add_argument("--sky-gradient-deg", type=float_arg, default=0.0,
                   help="direction the sky brightens towards, deg (0 = image right, 90 = image down)")
    s.add_argument("--jpeg-quality", type=int, default=None,
                   help="write a JPEG at this quality, 1-100 (16-bit images scaled to 8 bit by the background "
                        "noise first); an --out ending in .jpg alone means quality 95")
    s.add_argument("--out", required=True,
                   help="output PNG or JPEG (.jpg) (truth next to it as .json); with --frames a folder (made if it is not "
                        "there: frame_000.png ... and sequence.json in it; a name ending in .json writes "
                        "NAME_000.png ... and NAME.json beside each other instead)")
    s.add_argument("--force", action="store_true", help="overwrite existing files")
    s.set_defaults(func=cmd_simulate)
