"""The instrument's physics beyond the ideal model: named variants and seeded random draws.

``Physics`` holds every parameter of the effects that SCAN_BUNDLE.md allows and that the
noise presets (``noise.py``) do not cover: modulation that varies with period (projector
defocus, a projector pixel grid with quantised levels, a projector response that adds
harmonics), phase-step errors, modulation that varies per azimuth and across the field,
light scattered inside the clay, interreflection and a uniform veil, specular lobes,
dark or glossy clay, hot pixels, a support around the tablet, the tablet's shape, and
camera overrides (PSF, response gamma, bit depth, irradiance non-uniformity, exposures).

The defaults are the ideal instrument: ``Physics()`` changes nothing, so every preset
renders bit for bit what it rendered before physics variants existed (tested). Camera
fields left at ``None`` keep the noise preset's value.

``PHYSICS_VARIANTS`` isolates one effect per name (plus ``paper-like``, the issue-14 rig);
``draw_physics(seed)`` draws every parameter from the ranges of issue 14.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from worker.simulate.noise import NoiseModel
from worker.simulate.tablet import SHAPES

__all__ = [
    "IDEAL",
    "PHYSICS_VARIANTS",
    "SHAPES",
    "SUPPORTS",
    "Physics",
    "draw_physics",
    "physics_from_dict",
    "physics_to_dict",
    "resolve_physics",
]

SUPPORTS = ("velvet", "vblock", "cloth")


@dataclass(frozen=True)
class Physics:
    """Parameters of the non-ideal instrument and scene (lengths in µm on the object plane).

    Projector (fringe frames only):
      modulation: m0, the displayed pattern's contrast (None: the noise preset's m);
      projector_defocus_um: σ of the projector's Gaussian defocus; a sinusoid of period P
        keeps m·exp(-2π²σ²/P²) of its modulation;
      projector_pixel_um: projector pixel pitch along the fringe direction (0: continuous);
      projector_levels: grey levels the projector displays (0: continuous);
      projector_gamma: projector response (displayed value → light), adds harmonics;
      phase_step_error_deg: σ of each frame's error on its nominal phase step;
      modulation_azimuth_spread: m scaled per azimuth by a factor drawn in [1 - x, 1];
      modulation_field_variation: m scaled across the field by a smooth factor in [1 - x, 1].
    Clay:
      subsurface_um, subsurface_fraction: a fraction f of the projected pattern is
        scattered inside the clay with a Gaussian kernel of σ = subsurface_um before it
        is shaded (m(P) falls by (1 - f) + f·exp(-2π²σ²/P²));
      albedo_scale: multiplies the clay's reflectance (dark clay < 1); also in gt/albedo;
      specular_lobes: ((weight, Blinn-Phong exponent), ...) replacing the noise preset's lobe.
    Scene:
      interreflection: fraction of a low-passed copy (σ = interreflection_um) of the object
        frame added where the surface is concave (second bounce);
      veil: uniform stray light, a fraction of each lit frame's mean radiance;
      support: what the tablet lies on (``velvet``: the dark matte plane; ``vblock``;
        ``cloth``), seen in the background, never in the gt mask;
      shape: the synthetic tablet's body (``standard``, ``flat``, ``curved``, ``broken``).
    Camera (None: the noise preset's value):
      psf_sigma_px, psf_calibrated (write camera.psf_sigma_px in the manifest),
      bit_depth, response_gamma, irradiance_variation (± relative non-uniformity of E),
      object_exposure (>= 1) and reference_exposure (<= 1), hot_pixel_fraction.
    """

    name: str = "ideal"
    modulation: float | None = None
    projector_defocus_um: float = 0.0
    projector_pixel_um: float = 0.0
    projector_levels: int = 0
    projector_gamma: float = 1.0
    phase_step_error_deg: float = 0.0
    modulation_azimuth_spread: float = 0.0
    modulation_field_variation: float = 0.0
    subsurface_um: float = 0.0
    subsurface_fraction: float = 1.0
    albedo_scale: float = 1.0
    specular_lobes: tuple[tuple[float, float], ...] | None = None
    interreflection: float = 0.0
    interreflection_um: float = 1500.0
    veil: float = 0.0
    support: str = "velvet"
    shape: str = "standard"
    psf_sigma_px: float | None = None
    psf_calibrated: bool = False
    bit_depth: int | None = None
    response_gamma: float | None = None
    irradiance_variation: float | None = None
    object_exposure: float | None = None
    reference_exposure: float | None = None
    hot_pixel_fraction: float = 0.0

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"physics.{name}: must be {what}, got {getattr(self, name)!r}")

        m = self.modulation
        check("modulation", m is None or 0 < m <= 1, "in (0, 1]")
        for name in (
            "projector_defocus_um",
            "projector_pixel_um",
            "phase_step_error_deg",
            "subsurface_um",
            "interreflection",
            "veil",
            "hot_pixel_fraction",
        ):
            check(name, np.isfinite(getattr(self, name)) and getattr(self, name) >= 0, ">= 0")
        check(
            "projector_levels",
            self.projector_levels == 0 or self.projector_levels >= 2,
            "0 or >= 2",
        )
        check("projector_gamma", 0 < self.projector_gamma <= 5, "in (0, 5]")
        for name in ("modulation_azimuth_spread", "modulation_field_variation"):
            check(name, 0 <= getattr(self, name) < 1, "in [0, 1)")
        check("subsurface_fraction", 0 <= self.subsurface_fraction <= 1, "in [0, 1]")
        check("albedo_scale", 0 < self.albedo_scale <= 2, "in (0, 2]")
        check("interreflection_um", self.interreflection_um > 0, "> 0")
        check("support", self.support in SUPPORTS, f"one of {SUPPORTS}")
        check("shape", self.shape in SHAPES, f"one of {SHAPES}")
        check("hot_pixel_fraction", self.hot_pixel_fraction <= 0.01, "<= 0.01")
        if self.specular_lobes is not None:
            lobes = self.specular_lobes
            check(
                "specular_lobes",
                all(len(lb) == 2 and lb[0] >= 0 and lb[1] > 0 for lb in lobes),
                "pairs (weight >= 0, exponent > 0)",
            )
        check(
            "psf_sigma_px", self.psf_sigma_px is None or 0 <= self.psf_sigma_px <= 10, "in [0, 10]"
        )
        bd = self.bit_depth
        check("bit_depth", bd is None or (isinstance(bd, int) and 8 <= bd <= 16), "an int 8..16")
        g = self.response_gamma
        check("response_gamma", g is None or 0 < g <= 5, "in (0, 5]")
        v = self.irradiance_variation
        check("irradiance_variation", v is None or 0 <= v < 1, "in [0, 1)")
        e = self.object_exposure
        check("object_exposure", e is None or 1 <= e <= 100, "in [1, 100]")
        e = self.reference_exposure
        check("reference_exposure", e is None or 0.01 <= e <= 1, "in [0.01, 1]")

    @property
    def is_ideal(self) -> bool:
        """True when nothing differs from the ideal instrument (the name aside)."""
        return dataclasses.replace(self, name="ideal") == IDEAL

    @property
    def projector_is_sinusoid(self) -> bool:
        """The projected profile is a pure sinusoid (no pixel grid, levels or response)."""
        return (
            self.projector_pixel_um == 0
            and self.projector_levels == 0
            and self.projector_gamma == 1
        )

    def camera(self, noise: NoiseModel) -> NoiseModel:
        """The noise model with this physics' camera overrides (``noise`` itself if none).

        Idempotent: applying it to its own result changes nothing.
        """
        changes: dict = {}
        for mine, theirs in (
            ("modulation", "fringe_modulation"),
            ("psf_sigma_px", "blur_sigma_px"),
            ("bit_depth", "bit_depth"),
            ("response_gamma", "response_gamma"),
            ("irradiance_variation", "irradiance_variation"),
        ):
            value = getattr(self, mine)
            if value is not None and value != getattr(noise, theirs):
                changes[theirs] = value
        if self.specular_lobes is not None and noise.specular_weight != 0:
            changes["specular_weight"] = 0.0  # the lobes below replace the preset's
        if self.object_exposure is not None or self.reference_exposure is not None:
            obj = self.object_exposure or max(max(noise.exposures), 1.0)
            ref = self.reference_exposure or min(min(noise.exposures), 1.0)
            exposures = tuple(sorted({float(ref), float(obj)}))
            if exposures != noise.exposures:
                changes["exposures"] = exposures
        return dataclasses.replace(noise, **changes) if changes else noise

    def calibrated_psf_px(self, noise: NoiseModel) -> float | None:
        """camera.psf_sigma_px for the manifest: the true σ if calibrated, else None."""
        return float(self.camera(noise).blur_sigma_px) if self.psf_calibrated else None


IDEAL = Physics()


def _variants() -> dict[str, Physics]:
    v = [
        IDEAL,
        Physics("projector-mtf", projector_defocus_um=45.0),
        Physics(
            "projector-pixels",
            projector_pixel_um=40.0,
            projector_levels=64,
            projector_defocus_um=15.0,
        ),
        Physics("harmonics", projector_gamma=2.2),
        Physics("phase-steps", phase_step_error_deg=3.0),
        Physics("modulation-field", modulation_azimuth_spread=0.4, modulation_field_variation=0.4),
        Physics("subsurface", subsurface_um=80.0, subsurface_fraction=0.7),
        Physics("interreflection", interreflection=0.3, interreflection_um=1500.0, veil=0.02),
        Physics("specular", specular_lobes=((0.1, 15.0), (0.1, 300.0))),
        Physics("glossy-dark", albedo_scale=0.35, specular_lobes=((0.2, 60.0),)),
        Physics("hdr-16bit", bit_depth=16, response_gamma=1.0),
        Physics("low-bit", bit_depth=8),
        Physics("gamma", response_gamma=2.4),
        Physics("psf", psf_sigma_px=1.5, psf_calibrated=True),
        Physics("psf-unknown", psf_sigma_px=1.5),
        Physics("irradiance", irradiance_variation=0.3),
        Physics("exposures", object_exposure=2.0, reference_exposure=0.5),
        Physics("hot-pixels", hot_pixel_fraction=0.002),
        Physics("support-vblock", support="vblock"),
        Physics("support-cloth", support="cloth"),
        Physics("flat", shape="flat"),
        Physics("curved", shape="curved"),
        Physics("broken", shape="broken"),
        # The rig of issue 14's third row: 10-bit, projector pixels, defocus, light in the clay.
        Physics(
            "paper-like",
            modulation=0.8,
            projector_defocus_um=25.0,
            projector_pixel_um=30.0,
            projector_levels=256,
            projector_gamma=1.3,
            phase_step_error_deg=1.0,
            subsurface_um=60.0,
            subsurface_fraction=0.5,
            bit_depth=10,
            psf_sigma_px=0.5,
            psf_calibrated=True,
        ),
    ]
    return {p.name: p for p in v}


PHYSICS_VARIANTS: dict[str, Physics] = _variants()


def draw_physics(seed: int) -> Physics:
    """A random instrument over issue 14's ranges; the same seed gives the same draw.

    Each effect is on with a probability so that draws mix clean and hard instruments.
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"physics_seed: must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng([int(seed), 0x9A5])

    def maybe(p: float, value, off):
        return value if rng.uniform() < p else off

    def u(lo: float, hi: float) -> float:
        return round(float(rng.uniform(lo, hi)), 4)

    pixel = maybe(0.6, u(15.0, 60.0), 0.0)
    levels = int(2 ** rng.integers(5, 9)) if pixel > 0 else 0
    lobes = []
    for exponent in ((u(4.0, 30.0)), (u(100.0, 1000.0))):
        if rng.uniform() < 0.6:
            lobes.append((u(0.0, 0.2), exponent))
    exposures = rng.uniform() < 0.5
    return Physics(
        name=f"random-{int(seed)}",
        modulation=u(0.5, 0.95),
        projector_defocus_um=maybe(0.8, u(0.0, 70.0), 0.0),
        projector_pixel_um=pixel,
        projector_levels=levels,
        projector_gamma=maybe(0.5, u(1.0, 2.4), 1.0),
        phase_step_error_deg=maybe(0.5, u(0.0, 3.0), 0.0),
        modulation_azimuth_spread=u(0.0, 0.25),
        modulation_field_variation=u(0.0, 0.3),
        subsurface_um=maybe(0.7, u(10.0, 150.0), 0.0),
        subsurface_fraction=u(0.2, 0.9),
        albedo_scale=round(float(np.exp(rng.uniform(np.log(0.3), np.log(1.2)))), 4),
        specular_lobes=tuple(lobes),
        interreflection=maybe(0.7, u(0.0, 0.4), 0.0),
        interreflection_um=u(500.0, 3000.0),
        veil=maybe(0.5, u(0.0, 0.03), 0.0),
        support=str(rng.choice(SUPPORTS)),
        shape=str(rng.choice(SHAPES)),
        psf_sigma_px=u(0.0, 1.5),
        psf_calibrated=bool(rng.uniform() < 0.5),
        bit_depth=int(rng.integers(8, 17)),
        response_gamma=maybe(0.7, u(1.0, 2.4), 1.0),
        irradiance_variation=u(0.0, 0.3),
        object_exposure=u(1.0, 2.5) if exposures else None,
        reference_exposure=u(0.4, 1.0) if exposures else None,
        hot_pixel_fraction=maybe(0.5, round(float(rng.uniform(0, 1e-3)), 6), 0.0),
    )


def resolve_physics(physics: str | Physics, physics_seed: int | None) -> Physics:
    """``physics`` as given, a named variant, or ``"random"`` drawn from ``physics_seed``."""
    if isinstance(physics, Physics):
        return physics
    if physics == "random":
        if physics_seed is None:
            raise ValueError("physics: 'random' needs a physics_seed")
        return draw_physics(physics_seed)
    try:
        return PHYSICS_VARIANTS[physics]
    except KeyError:
        raise ValueError(
            f"physics: unknown {physics!r}; choose 'random' or one of {sorted(PHYSICS_VARIANTS)}"
        ) from None


def physics_to_dict(physics: Physics) -> dict:
    """Plain JSON-ready dict of every field (tuples as lists)."""
    out = dataclasses.asdict(physics)
    if out["specular_lobes"] is not None:
        out["specular_lobes"] = [list(lb) for lb in out["specular_lobes"]]
    return out


def physics_from_dict(doc: dict) -> Physics:
    """Inverse of ``physics_to_dict``; ValueError naming an unknown or bad field."""
    if not isinstance(doc, dict):
        raise ValueError(f"physics: expected an object, got {type(doc).__name__}")
    names = {f.name for f in dataclasses.fields(Physics)}
    unknown = sorted(set(doc) - names)
    if unknown:
        raise ValueError(f"physics: unknown fields {unknown}")
    kwargs = dict(doc)
    lobes = kwargs.get("specular_lobes")
    if lobes is not None:
        try:
            kwargs["specular_lobes"] = tuple((float(w), float(a)) for w, a in lobes)
        except (TypeError, ValueError):
            raise ValueError(
                f"physics.specular_lobes: expected [[weight, exponent], ...], got {lobes!r}"
            ) from None
    try:
        return Physics(**kwargs)
    except TypeError as exc:  # a string where a number belongs, and the like
        raise ValueError(f"physics: a field has the wrong type ({exc})") from None
