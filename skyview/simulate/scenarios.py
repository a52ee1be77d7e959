"""Named test conditions, after the papers that defined them.

A scenario fixes the camera, the guide catalog's magnitude limit, the measurement noise and the
disturbances (false stars), so that every method is compared under identical conditions. The blind
scenarios (blind8, blind20, narrow4, and the telescope fields narrow1.5 and narrow1 rendered from the deep
catalog) add what real photographs have: field stars fainter than the
catalog, vignetting, a sky gradient, and optionally lens distortion and JPEG compression
(`skyview bench --blind`, docs/benchmarks.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from skyview.core.camera import Camera
from skyview.core.errors import BadInput


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    fov_deg: float
    width: int
    height: int
    mag_limit: float  # guide catalog and rendering limit (Hp)
    noise_rad: float  # 1-sigma direction error per star, added to the rendered positions
    n_false_stars: int = 0
    false_star_placement: str = "disk"  # Cole & Crassidis: within half the FOV of the boresight
    centroid_sigma_px: float = 0.1  # what the centroider adds on top of noise_rad (measured)
    max_stars: int = 40  # brightest centroids handed to the identifier (20 deg fields hold ~40-100)
    # real-world effects (skyview.simulate.render.simulate_image); all off by default
    faint_extra_mag: float = 0.0  # also render stars down to mag_limit + this (Hp, at most 9.0)
    vignetting: float = 0.0  # fraction of light lost at the image corners (cos^4-shaped profile)
    sky_gradient: float = 0.0  # fraction by which the sky differs across the frame (left to right)
    jpeg_quality: int | None = None  # the image goes through a JPEG at this quality (1..100)
    k1: float = 0.0  # radial distortion of the camera (OpenCV k1, k2), rendered and known to MethodSolver
    k2: float = 0.0
    # the stars rendered: "guide" (Hipparcos-2 to Hp 9) or "deep" (+ Gaia DR3 to G 10, skyview.core.deep_catalog:
    # the sky a telescope's narrow field shows)
    catalog: str = "guide"
    exposure_s: float = 0.1  # the sensor's (SensorModel.exposure_s): 2 s shows G 10 stars at SNR ~10
    bit_depth: int = 16  # the sensor's ADC
    bias_e: float = 100.0  # the sensor's pedestal (electrons; 15 e- is a background of ~2 DN at 8 bits)
    image_circle_deg: float | None = None  # a circular fisheye: stars drawn only this far from the boresight
    lens: str = "pinhole"  # the camera model (skyview.core.camera): pinhole, equidistant or equisolid fisheye
    frames: int = 0  # a slew of this many frames (skyview.bench.runner.run_slew_bench); 0: single frames
    step_deg: float = 2.0  # the slew's turn per frame about the camera y axis

    @property
    def is_slew(self) -> bool:
        return self.frames > 0

    def camera(self) -> Camera:
        return Camera.from_fov(self.fov_deg, self.width, self.height, k1=self.k1, k2=self.k2, model=self.lens)

    def sensor(self):
        """The default sensor (`skyview.simulate.render.SensorModel`) at this scenario's exposure."""
        from skyview.simulate.render import SensorModel  # (the renderer imports scipy: not on a solve's path)

        return SensorModel(exposure_s=self.exposure_s, bit_depth=self.bit_depth, bias_e=self.bias_e)

    def render_kwargs(self) -> dict:
        """The keyword arguments of simulate_image this scenario fixes (besides camera, R, seed)."""
        kw = dict(mag_limit=self.mag_limit, n_false_stars=self.n_false_stars,
                  false_star_placement=self.false_star_placement, position_noise_rad=self.noise_rad)
        effects = dict(faint_extra_mag=self.faint_extra_mag, vignetting=self.vignetting,
                       sky_gradient=self.sky_gradient, jpeg_quality=self.jpeg_quality,
                       image_circle_deg=self.image_circle_deg)
        kw.update({k: v for k, v in effects.items() if v})  # off effects are not passed at all
        return kw

    def with_changes(self, **changes) -> "Scenario":
        """A copy with some fields changed (None values are ignored); the name records the changes."""
        changes = {k: v for k, v in changes.items() if v is not None}
        if not changes:
            return self
        tag = ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in changes.items())
        return replace(self, name=f"{self.name}[{tag}]", **changes)

    @property
    def sigma_rad(self) -> float:
        """The sigma an identifier should assume: scenario noise and centroid error combined."""
        pix = self.camera().pixel_scale_rad * self.centroid_sigma_px
        return float((self.noise_rad ** 2 + pix ** 2) ** 0.5)

    def to_dict(self) -> dict:
        return asdict(self)


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in [
        Scenario("cole8", "Cole & Crassidis: 8 deg FOV, 1024x1024, Hp <= 6.0, 87 urad noise",
                 fov_deg=8.0, width=1024, height=1024, mag_limit=6.0, noise_rad=87e-6),
        Scenario("cole8-false", "cole8 with one false star (debris) within half the FOV of the boresight",
                 fov_deg=8.0, width=1024, height=1024, mag_limit=6.0, noise_rad=87e-6, n_false_stars=1),
        Scenario("cole8-hp62", "cole8 at the paper's catalog depth: Hp <= 6.2, where the catalog's pairs within 8 deg "
                 "(93,434) come nearest the paper's 106,308 angles at the depth the paper names (6.0: 59,622)",
                 fov_deg=8.0, width=1024, height=1024, mag_limit=6.2, noise_rad=87e-6),
        Scenario("cole8-hp62-false", "cole8-hp62 with one false star within half the FOV of the boresight",
                 fov_deg=8.0, width=1024, height=1024, mag_limit=6.2, noise_rad=87e-6, n_false_stars=1),
        Scenario("udomkesmalee30", "Udomkesmalee et al.: 30 deg FOV, 1024x1024, Hp <= 4.5, 1 deg noise per axis "
                 "(the paper's '10' read as 1 deg) and 0.6 mag (docs/stochastic.md)",
                 fov_deg=30.0, width=1024, height=1024, mag_limit=4.5, noise_rad=0.017453292519943295),
        Scenario("juang8", "Juang, Kim & Junkins: 8x8 deg FOV, 1024x1024, Hp <= 7.3 (the paper: 7.3 Mv), 87 urad "
                 "noise (the paper states none: cole8's, same camera)",
                 fov_deg=8.0, width=1024, height=1024, mag_limit=7.3, noise_rad=87e-6),
        Scenario("sun20", "Sun, Qi, Jin & Wang: 20x20 deg FOV, 1024x1024, Hp <= 6.0, 10 urad noise (the paper "
                 "states none; its eps threshold 0.001 holds the true pattern at ~10 urad)",
                 fov_deg=20.0, width=1024, height=1024, mag_limit=6.0, noise_rad=10e-6, max_stars=200),
        Scenario("blind8", "blind solving, 8 deg FOV, 1024x768, every catalog star rendered (Hp 6.5 + 2.5 fainter "
                 "field stars, to Hp 9.0, as the real sky has them), 30 % vignetting at the corners, 20 % sky "
                 "gradient; positions from the image only",
                 fov_deg=8.0, width=1024, height=768, mag_limit=6.5, noise_rad=0.0,
                 faint_extra_mag=2.5, vignetting=0.3, sky_gradient=0.2),
        Scenario("blind20", "blind solving, 20 deg FOV, 1024x768, every catalog star rendered (Hp 6.0 + 3.0 fainter "
                 "field stars, to Hp 9.0), 30 % vignetting at the corners, 20 % sky gradient",
                 fov_deg=20.0, width=1024, height=768, mag_limit=6.0, noise_rad=0.0,
                 faint_extra_mag=3.0, vignetting=0.3, sky_gradient=0.2),
        Scenario("narrow4", "blind solving, 4 deg FOV, 1024x768, stars rendered to Hp 7.5 + fainter field stars "
                 "to Hp 9.0, 30 % vignetting at the corners, 20 % sky gradient",
                 fov_deg=4.0, width=1024, height=768, mag_limit=7.5, noise_rad=0.0,
                 faint_extra_mag=1.5, vignetting=0.3, sky_gradient=0.2),
        Scenario("faint6", "blind solving of a star tracker's faint frames: 6 deg FOV, 1280x1024, 8 bit, 30 ms "
                 "exposure, a background of ~2 DN (15 e- pedestal), every catalog star rendered (to Hp 9): Hp 6 "
                 "stars at SNR ~10",
                 fov_deg=6.0, width=1280, height=1024, mag_limit=6.0, noise_rad=0.0, faint_extra_mag=3.0,
                 exposure_s=0.03, bit_depth=8, bias_e=15.0),
        Scenario("fisheye120", "blind solving through a wide fisheye: equidistant lens, 120 deg across, 1280x960, "
                 "Hp <= 5.0 + fainter field stars to Hp 7.0, 30 % vignetting (cos^4-shaped in the off-axis angle)",
                 fov_deg=120.0, width=1280, height=960, mag_limit=5.0, noise_rad=0.0, faint_extra_mag=2.0,
                 vignetting=0.3, lens="equidistant", max_stars=40),
        Scenario("allsky180", "blind solving of an all-sky camera: equisolid fisheye, 180 deg across a 1024x1024 "
                 "sensor, the sky to its horizon (90 deg from the zenith; the corners dark), Hp <= 4.0 + fainter "
                 "field stars to Hp 6.0, k1 = 0.01 (its lens' own distortion)",
                 fov_deg=180.0, width=1024, height=1024, mag_limit=4.0, noise_rad=0.0, faint_extra_mag=2.0,
                 lens="equisolid", k1=0.01, max_stars=40, image_circle_deg=90.0),
        Scenario("narrow1.5", "blind solving of a telescope's field: 1.5 deg FOV, 1024x768, every star of the deep "
                 "catalog rendered (Hipparcos-2 + Gaia DR3 to G 10), 2 s exposure, 30 % vignetting at the corners, "
                 "20 % sky gradient",
                 fov_deg=1.5, width=1024, height=768, mag_limit=10.0, noise_rad=0.0, vignetting=0.3,
                 sky_gradient=0.2, catalog="deep", exposure_s=2.0),
        Scenario("narrow1", "narrow1.5 at 1.0 deg FOV (a median of 8 stars to G 10 in the field)",
                 fov_deg=1.0, width=1024, height=768, mag_limit=10.0, noise_rad=0.0, vignetting=0.3,
                 sky_gradient=0.2, catalog="deep", exposure_s=2.0),
        Scenario("slew", "tracking: a slew of 10 frames turning 2 deg per frame about the camera "
                 "y axis (a pan), 12 deg FOV, 1024x1024, Hp <= 6.0, no noise beyond the centroider's "
                 "(skyview.solver.track; `skyview bench --scenario slew`)",
                 fov_deg=12.0, width=1024, height=1024, mag_limit=6.0, noise_rad=0.0, frames=10),
        Scenario("slew8", "tracking through sparse sky: a slew of 20 frames turning 2 deg per frame about the camera "
                 "y axis, 8 deg FOV, 1024x1024, Hp <= 6.0 (frames with 2-3 stars are common)",
                 fov_deg=8.0, width=1024, height=1024, mag_limit=6.0, noise_rad=0.0, frames=20),
    ]
}
# the slew scenarios' motion (skyview.bench.runner.run_slew_bench)
SLEW = "slew"
SLEW_FRAMES = 10
SLEW_STEP_DEG = 2.0
SLEW_AXIS = "y"


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise BadInput(f"unknown scenario {name!r}: choose from {', '.join(SCENARIOS)}") from None
