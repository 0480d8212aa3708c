"""Scene spec v1: the one JSON contract shared by the CLI, the HTTP API and the worker.

See docs/method.md, "Scene spec v1" (and v1.1's ``medium.phase``). Units: world units for
lengths, degrees for ``fov``, ``density_scale`` multiplies grid values into sigma_t per world
unit.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from .errors import SceneError

Vec3 = tuple[float, float, float]
Unit = Annotated[float, Field(ge=0.0, le=1.0)]
NonNegative = Annotated[float, Field(ge=0.0)]


def _norm(v: Vec3) -> float:
    return math.sqrt(sum(c * c for c in v))


def _finite(v: Vec3, what: str) -> Vec3:
    if not all(math.isfinite(c) for c in v):
        raise ValueError(f"{what} must be three finite numbers, got {list(v)}")
    return v


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class VolumeSpec(_Model):
    """Where the density grid comes from: a file ``path`` (CLI) or an uploaded volume ``id`` (API)."""

    path: str | None = Field(None, description="A .vdb or .vol file, relative to the scene file")
    id: str | None = Field(None, description="An uploaded volume's id (HTTP API)")
    grid: str | None = Field(None, description="Grid name; default 'density', else the only float grid")
    scale: float = Field(
        1.0, gt=0.0, description="Uniform scale about the origin, after the grid's transform"
    )

    @model_validator(mode="after")
    def _one_source(self) -> VolumeSpec:
        if (self.path is None) == (self.id is None):
            raise ValueError("give exactly one of 'path' (a .vdb/.vol file) or 'id' (an uploaded volume)")
        return self


#: Largest |g| of a Henyey-Greenstein lobe (scene spec v1.1).
MAX_G = 0.95
PHASE_TYPES = ("isotropic", "hg", "hg2")
Asymmetry = Annotated[float, Field(ge=-MAX_G, le=MAX_G)]


def _number(v, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{what} must be a finite number, got {v!r}")
    return float(v)


def _asymmetry(v, what: str) -> float:
    g = _number(v, what)
    if abs(g) > MAX_G:
        raise ValueError(f"{what} must be in [-{MAX_G}, {MAX_G}] (g > 0 scatters forward), got {g:g}")
    return g


class PhaseSpec(_Model):
    """The phase function (scene spec v1.1): ``isotropic``; ``hg``, Henyey-Greenstein of
    asymmetry ``g`` (Mitsuba's sign: g > 0 scatters forward); ``hg2``, a blend of two HG lobes
    ``g`` = [g1, g2], ``weight`` that of the first (Mitsuba's ``blendphase``)."""

    type: Literal["isotropic", "hg", "hg2"] = "isotropic"
    g: Asymmetry | tuple[Asymmetry, Asymmetry] | None = Field(
        None, description=f"hg: the asymmetry in [-{MAX_G}, {MAX_G}], > 0 forward; hg2: [g1, g2]"
    )
    weight: Unit | None = Field(None, description="hg2: the first lobe's weight, in [0, 1]")

    @model_validator(mode="before")
    @classmethod
    def _check(cls, data):
        # One check per type, each naming its field (a union of models would name the tag too)
        if not isinstance(data, dict):
            return data
        kind, g, weight = data.get("type", "isotropic"), data.get("g"), data.get("weight")
        if kind not in PHASE_TYPES:
            raise ValueError(f"type must be one of {', '.join(PHASE_TYPES)}, got {kind!r}")
        unknown = sorted(set(data) - {"type", "g", "weight"})
        if unknown:
            raise ValueError(f"unknown field {unknown[0]!r} (a phase has type, g and weight)")
        if kind == "isotropic" and (g is not None or weight is not None):
            raise ValueError("an isotropic phase takes no g or weight")
        if kind == "hg":
            if g is None:
                raise ValueError("g is required for type 'hg' (the asymmetry, g > 0 forward)")
            if weight is not None:
                raise ValueError("weight is for type 'hg2' (two lobes), not 'hg'")
            return {"type": kind, "g": _asymmetry(g, "g")}
        if kind == "hg2":
            if not isinstance(g, list | tuple) or len(g) != 2:
                raise ValueError(f"g must be two asymmetries [g1, g2] for type 'hg2', got {g!r}")
            if weight is None:
                raise ValueError("weight is required for type 'hg2' (the first lobe's, in [0, 1])")
            w = _number(weight, "weight")
            if not 0.0 <= w <= 1.0:
                raise ValueError(f"weight must be in [0, 1] (the first lobe's), got {w:g}")
            return {"type": kind, "g": (_asymmetry(g[0], "g[0]"), _asymmetry(g[1], "g[1]")), "weight": w}
        return data

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        return {k: v for k, v in handler(self).items() if v is not None}

    def lobes(self) -> tuple[tuple[float, float], ...]:
        """((weight, g), ...): one lobe for isotropic and hg (isotropic is g = 0), two for hg2."""
        if self.type == "hg2":
            return ((self.weight, self.g[0]), (1.0 - self.weight, self.g[1]))
        return ((1.0, float(self.g) if self.type == "hg" else 0.0),)

    @property
    def isotropic(self) -> bool:
        """Whether the phase is the isotropic one (an hg of g = 0 is): it then renders, and is
        cached, exactly as isotropic."""
        return all(g == 0.0 for w, g in self.lobes() if w > 0.0)

    def mean_cosine(self) -> float:
        """g_eff, the mean cosine of the scattering angle: sum of weight * g over the lobes."""
        return float(sum(w * g for w, g in self.lobes()))


class MediumSpec(_Model):
    """sigma_t(x) = density(x) * density_scale; albedo = sigma_s / sigma_t; the phase function
    (isotropic by default)."""

    density_scale: NonNegative = 1.0
    albedo: Unit | tuple[Unit, Unit, Unit] = 1.0
    phase: PhaseSpec = PhaseSpec()

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A v1 medium dumps as it did before v1.1 (request hashes, job payloads): no phase
        d = handler(self)
        if self.phase.type == "isotropic":
            d.pop("phase", None)
        return d

    def albedo_rgb(self) -> Vec3:
        a = self.albedo
        return (a, a, a) if isinstance(a, float | int) else tuple(a)

    def graph_medium(self) -> tuple[float, Vec3]:
        """(density_scale', albedo') of the isotropic medium whose graph stands in for multiple
        scattering (docs/method.md, "Anisotropic scattering"): the similarity relations
        sigma_s' = sigma_s (1 - g), sigma_a' = sigma_a, i.e.

            sigma_t' = sigma_t (1 - a g),   albedo' = a (1 - g) / (1 - a g),

        with g the phase's mean cosine. sigma_t' must be grey (the graph depends on sigma_t
        only), so ``a`` in sigma_t' is the mean of the channels, and albedo' keeps each
        channel's absorption exact, sigma_a' = sigma_a: albedo'_c = (a_c - a g) / (1 - a g)
        (the same for a grey albedo; at least 0). A channel that does not absorb stays so.
        The isotropic phase returns the medium itself."""
        albedo = self.albedo_rgb()
        if self.phase.isotropic:
            return self.density_scale, albedo
        g = self.phase.mean_cosine()
        a_g = g * sum(albedo) / 3.0
        k = 1.0 - a_g
        return self.density_scale * k, tuple(min(1.0, max(0.0, (a - a_g) / k)) for a in albedo)


class LightSpec(_Model):
    """A directional light; ``direction`` is where the light travels (Mitsuba's convention)."""

    type: Literal["directional"] = "directional"
    direction: Vec3 = (0.0, -1.0, 0.0)
    irradiance: NonNegative | tuple[NonNegative, NonNegative, NonNegative] = 1.0

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v: Vec3) -> Vec3:
        _finite(v, "direction")
        if _norm(v) < 1e-9:
            raise ValueError("direction must be a non-zero vector (the way the light travels)")
        return v

    def irradiance_rgb(self) -> Vec3:
        e = self.irradiance
        return (e, e, e) if isinstance(e, float | int) else tuple(e)

    def unit_direction(self) -> Vec3:
        n = _norm(self.direction)
        return tuple(c / n for c in self.direction)

    def intensity_rgb(self) -> Vec3:
        return self.irradiance_rgb()


class SkySpec(_Model):
    """A uniform environment of ``radiance`` from every direction (Mitsuba's ``constant``), seen
    behind and through the medium (scene spec v1.1)."""

    type: Literal["sky"] = "sky"
    radiance: NonNegative | tuple[NonNegative, NonNegative, NonNegative] = 1.0

    @field_validator("radiance", mode="before")
    @classmethod
    def _intensity(cls, v):
        # one message, not one per member of the scalar | RGB union
        values = v if isinstance(v, list | tuple) else [v]

        def number(c) -> bool:
            return not isinstance(c, bool) and isinstance(c, int | float) and math.isfinite(c) and c >= 0

        ok = len(values) in (1, 3) and all(number(c) for c in values)
        if not ok or (isinstance(v, list | tuple) and len(v) != 3):
            raise ValueError(f"must be a non-negative number or three of them (RGB), got {v!r}")
        return v

    def intensity_rgb(self) -> Vec3:
        e = self.radiance
        return (e, e, e) if isinstance(e, float | int) else tuple(e)


class EnvmapSpec(_Model):
    """A lat-long HDR environment (Mitsuba's ``envmap``, the same orientation: the image's top
    row is +y), from a ``path`` (CLI: an .exr file, relative to the scene file) or an uploaded
    image's ``id`` (HTTP API), times ``scale``; seen behind and through the medium (v1.1)."""

    type: Literal["envmap"] = "envmap"
    path: str | None = Field(None, description="An .exr file, relative to the scene file")
    id: str | None = Field(None, description="An uploaded environment's id (HTTP API)")
    scale: float = Field(1.0, ge=0.0, le=1e6, description="Multiplies the image's radiance")

    @model_validator(mode="after")
    def _one_source(self) -> EnvmapSpec:
        if (self.path is None) == (self.id is None):
            raise ValueError("give exactly one of 'path' (an .exr file) or 'id' (an uploaded environment)")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        return {k: v for k, v in handler(self).items() if v is not None}

    def intensity_rgb(self) -> Vec3:
        return (self.scale,) * 3


class SunskySpec(_Model):
    """The sun and a clear sky of the Hosek-Wilkie model (Mitsuba's ``sunsky``): the sun toward
    ``sun_direction``, above the horizon of the zenith ``up``, the sky's haze by ``turbidity``,
    the ground below the sky by its albedo; ``sun_scale`` and ``sky_scale`` multiply either part
    (Mitsuba's units: the sun's irradiance is about 1.5 at 60 degrees up). The engine takes the
    sun as a directional light and the sky as an environment map (sunsky.py), volpath the model
    itself (v1.1)."""

    type: Literal["sunsky"] = "sunsky"
    sun_direction: Vec3 = Field((0.0, 0.866, 0.5), description="Toward the sun, above the horizon")
    up: Vec3 = Field((0.0, 1.0, 0.0), description="The zenith (a z-up volume's scene: [0, 0, 1])")
    turbidity: float = Field(3.0, ge=1.0, le=10.0, description="Haze: 2 arctic, 3 clear, 6 warm, 10 hazy")
    ground_albedo: float = Field(0.3, ge=0.0, le=1.0, description="The ground's albedo (Mitsuba's 'albedo')")
    sun_scale: float = Field(1.0, ge=0.0, le=1e6, description="Multiplies the sun's light")
    sky_scale: float = Field(1.0, ge=0.0, le=1e6, description="Multiplies the sky's light")

    @field_validator("sun_direction", "up")
    @classmethod
    def _nonzero(cls, v: Vec3, info) -> Vec3:
        _finite(v, info.field_name)
        if _norm(v) < 1e-9:
            raise ValueError(f"{info.field_name} must be a non-zero vector")
        return v

    @model_validator(mode="after")
    def _above(self) -> SunskySpec:
        if sum(s * u for s, u in zip(self.unit_sun_direction(), self.unit_up(), strict=True)) < 0.0:
            raise ValueError(
                f"sun_direction must point above the horizon (of up {list(self.up)}), "
                f"got {list(self.sun_direction)}"
            )
        return self

    def unit_sun_direction(self) -> Vec3:
        n = _norm(self.sun_direction)
        return tuple(c / n for c in self.sun_direction)

    def unit_up(self) -> Vec3:
        n = _norm(self.up)
        return tuple(c / n for c in self.up)


#: Most lights in a scene's ``lights`` (scene spec v1.1).
MAX_LIGHTS = 8
Light = Annotated[LightSpec | SkySpec | EnvmapSpec | SunskySpec, Field(discriminator="type")]
LIGHT_TYPES = {"directional": LightSpec, "sky": SkySpec, "envmap": EnvmapSpec, "sunsky": SunskySpec}


def check_light_list(data):
    """A model's input ``data`` whose ``lights`` is checked light by light, each error named
    lights.<i>.<field> (a tagged union's errors would name the tag and every member), and never
    given with ``light``."""
    if not isinstance(data, dict) or data.get("lights") is None:
        return data
    if "light" in data:
        raise ValueError("give 'light' (one directional light) or 'lights' (a list), not both")
    lights = data["lights"]
    if not isinstance(lights, list | tuple) or not 1 <= len(lights) <= MAX_LIGHTS:
        raise ValueError(f"lights must be a list of 1 to {MAX_LIGHTS} lights, got {_brief(lights)}")
    for i, light in enumerate(lights):
        if isinstance(light, LightSpec | SkySpec | EnvmapSpec | SunskySpec):  # already a checked light
            continue
        kind = light.get("type") if isinstance(light, dict) else None
        if not isinstance(kind, str) or kind not in LIGHT_TYPES:
            raise ValueError(f"lights.{i}.type must be one of {', '.join(LIGHT_TYPES)}, got {kind!r}")
        try:
            LIGHT_TYPES[kind].model_validate(light)
        except ValidationError as err:
            parts = format_validation_error(err).split("; ")
            raise ValueError("; ".join(f"lights.{i}.{part}" for part in parts)) from None
    components = sum(2 if _type(light) == "sunsky" else 1 for light in lights)
    if components > MAX_LIGHTS:
        raise ValueError(
            f"lights make at most {MAX_LIGHTS} light components (a sunsky is two: its sun and its "
            f"sky), got {components}"
        )
    return data


def _type(light) -> str:
    return light.type if isinstance(light, _Model) else light["type"]


def _brief(v) -> str:
    return f"{len(v)} of them" if isinstance(v, list | tuple) else repr(v)[:40]


class CameraSpec(_Model):
    """Pinhole camera, look_at(eye, target, up), ``fov`` in degrees along the image width."""

    eye: Vec3
    target: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = Field(40.0, gt=0.0, lt=180.0)
    width: int = Field(256, ge=1, le=4096)
    height: int = Field(256, ge=1, le=4096)

    @model_validator(mode="after")
    def _geometry(self) -> CameraSpec:
        _finite(self.eye, "eye")
        _finite(self.target, "target")
        _finite(self.up, "up")
        view = tuple(t - e for t, e in zip(self.target, self.eye, strict=True))
        if _norm(view) < 1e-9:
            raise ValueError("eye and target must differ (the camera needs a viewing direction)")
        if _norm(self.up) < 1e-9:
            raise ValueError("up must be a non-zero vector")
        cross = (
            view[1] * self.up[2] - view[2] * self.up[1],
            view[2] * self.up[0] - view[0] * self.up[2],
            view[0] * self.up[1] - view[1] * self.up[0],
        )
        if _norm(cross) < 1e-6 * _norm(view) * _norm(self.up):
            raise ValueError("up must not be parallel to the viewing direction (target - eye)")
        return self


class RenderSpec(_Model):
    """Sampling settings; ``max_depth`` is the most scattering events on a path, -1 unbounded."""

    spp: int = Field(64, ge=1, le=65536)
    max_depth: int = Field(-1, ge=-1)
    seed: int = Field(0, ge=0, lt=2**31)


class Scene(_Model):
    """Scene spec v1, and v1.1's ``lights``: a list of lights instead of the one ``light``."""

    volume: VolumeSpec
    medium: MediumSpec = MediumSpec()
    light: LightSpec = LightSpec()
    lights: tuple[Light, ...] | None = Field(
        None,
        min_length=1,
        max_length=MAX_LIGHTS,
        description=f"v1.1: up to {MAX_LIGHTS} lights (directional, sky, envmap, sunsky) instead of 'light', "
        "never both",
    )
    camera: CameraSpec
    render: RenderSpec = RenderSpec()

    @model_validator(mode="before")
    @classmethod
    def _light_list(cls, data):
        return check_light_list(data)

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A v1 scene dumps as it did before v1.1 (request hashes, job payloads): no lights; a
        # v1.1 one without the unused default light
        d = handler(self)
        d.pop("light" if self.lights is not None else "lights", None)
        return d

    def light_list(self) -> tuple[LightSpec | SkySpec | EnvmapSpec | SunskySpec, ...]:
        """The scene's lights: ``lights``, or the one ``light`` of a v1 scene."""
        return self.lights if self.lights is not None else (self.light,)


def format_validation_error(err: ValidationError) -> str:
    """One line per problem, each naming the field: ``camera.fov: must be < 180``."""
    parts = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"] if not isinstance(p, int) or len(e["loc"]) < 3)
        msg = e["msg"].removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)


def parse_scene(data: dict | str, base_dir: str | Path | None = None) -> Scene:
    """Validates a scene spec (a dict or JSON text) and resolves ``volume.path`` against ``base_dir``.

    Raises:
        SceneError: with a message naming every invalid field.
    """
    try:
        scene = Scene.model_validate_json(data) if isinstance(data, str) else Scene.model_validate(data)
    except ValidationError as err:
        raise SceneError(f"invalid scene: {format_validation_error(err)}") from None
    if scene.volume.path is not None and base_dir is not None:
        path = Path(base_dir) / scene.volume.path
        scene = scene.model_copy(update={"volume": scene.volume.model_copy(update={"path": str(path)})})
    if scene.lights is not None and base_dir is not None:
        lights = tuple(
            li.model_copy(update={"path": str(Path(base_dir) / li.path)})
            if li.type == "envmap" and li.path is not None
            else li
            for li in scene.lights
        )
        scene = scene.model_copy(update={"lights": lights})
    return scene


def voxel_depth_problem(density_scale: float, value_max: float, voxel: float, limit: float) -> str | None:
    """Why ``density_scale`` is refused where one voxel (``voxel`` world units) at the densest
    ``value_max`` would be optically deeper than ``limit`` (options.MAX_VOXEL_TAU, or the API's
    setting), or None: delta tracking takes steps in proportion to the optical depth it crosses,
    and past the limit a render or a precompute runs for hours where it should refuse."""
    per_unit = float(value_max) * float(voxel)  # optical depth of one voxel at density_scale 1
    tau = density_scale * per_unit
    if tau <= limit:
        return None
    return (
        f"{density_scale:g} makes the optical depth across one voxel {tau:.3g} (densest value "
        f"{value_max:.3g}, voxel {voxel:.3g} world units), over the limit of {limit:g}; use at most "
        f"{limit / per_unit:.4g}"
    )


#: The largest radiance an environment map's pixel may hold: times the largest ``scale``
#: (EnvmapSpec, 1e6) and summed over the largest map (store.MAX_ENVMAP_PIXELS) it stays finite
#: in float32 (a map of 3e38 at scale 1e6 rendered inf).
MAX_ENVMAP_RADIANCE = 1e24


def envmap_problem(pixels) -> str | None:
    """Why an environment map's pixels are refused (negative, not finite, or over
    MAX_ENVMAP_RADIANCE), or None."""
    import numpy as np

    pixels = np.asarray(pixels)
    if not np.isfinite(pixels).all() or (pixels < 0).any():
        return "has negative or non-finite pixels: an environment map's radiance is >= 0"
    peak = float(pixels.max(initial=0.0))
    if peak > MAX_ENVMAP_RADIANCE:
        return f"has a pixel of radiance {peak:.3g}, over the limit of {MAX_ENVMAP_RADIANCE:g}"
    return None


def load_scene(path: str | Path) -> Scene:
    """Reads a scene spec JSON file; ``volume.path`` is relative to the file's folder."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneError(f"scene file not found: {path}") from None
    except OSError as err:
        raise SceneError(f"cannot read scene file {path}: {err.strerror}") from None
    except UnicodeDecodeError as err:
        raise SceneError(f"{path} is not UTF-8 text (byte {err.start}); a scene is a JSON file") from None
    try:
        json.loads(text)
    except json.JSONDecodeError as err:
        raise SceneError(
            f"{path} is not valid JSON: {err.msg} at line {err.lineno}, column {err.colno}"
        ) from None
    except RecursionError:
        raise SceneError(f"{path} nests its JSON too deeply to be a scene") from None
    return parse_scene(text, base_dir=path.parent)


def json_schema() -> dict:
    """The JSON schema of scene spec v1."""
    schema = Scene.model_json_schema()
    schema["$id"] = "https://cloudgraph.dev/schema/scene-v1.json"
    schema["title"] = "cloudgraph scene spec v1"
    return schema
