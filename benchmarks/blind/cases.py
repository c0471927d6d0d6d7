"""Worlds, scenes and cases of the broadened blind check (recon-bench diagnose-blind --worlds).

A world is where the observed images come from:
- ``own``: data_synth with recon's own rasterizer (capture.backend: own); camera effects only
  (the rasterizer cannot make light transport);
- ``mitsuba``: data_synth's path tracer (capture.backend: mitsuba) for every catalogue effect:
  shadows, interreflection and specular come from the path tracer, the camera effects are
  data_synth's world effects applied on top of the path-traced linear radiance;
- ``real``: photos of a real object (../shared/captures, fixed exposure) with known camera
  effects applied in linear space (benchmarks.blind.real), the untouched photos as the clean case.

A scene is a mesh and material; glossy variants carry a specular lobe that is always there (the
object is glossy), so their truth always holds ``specular``. Scenes in one ``group`` share a
mesh: leave-one-scene-out holds a whole group out.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED = REPO_ROOT.parent / "shared"
MESHES = SHARED / "meshes"

CAMERA_EFFECTS = (
    "exposure",
    "white_balance",
    "vignetting",
    "response_curve",
    "lens_distortion",
    "defocus_blur",
    "motion_blur",
    "pose_error",
)
LIGHT_TRANSPORT_EFFECTS = ("specular", "shadows", "interreflection")
# The camera effects the real-photo world injects (pose_error and motion blur need the capture
# geometry or a trajectory the photos do not have).
REAL_EFFECTS = (
    "exposure",
    "white_balance",
    "vignetting",
    "response_curve",
    "lens_distortion",
    "defocus_blur",
)
WORLDS = ("own", "mitsuba", "real")
# Effects physically present in every case of a world without being injected: naming them is
# neither required nor an error (scored apart, as "present, named"), and a clean case's evidence
# for them is no null measurement (left out of calibration). The path tracer traces the
# visibility of the scene's own sun, so its renders carry cast shadows; real photos carry the
# object's real light transport.
PRESENT_IN_WORLD: dict[str, tuple[str, ...]] = {
    "own": (),
    "mitsuba": ("shadows",),
    "real": LIGHT_TRANSPORT_EFFECTS,
}
# The order in which an interrupted run covers the effects: camera and light-transport effects
# alternate.
EFFECT_ORDER = (
    "exposure",
    "shadows",
    "vignetting",
    "specular",
    "lens_distortion",
    "interreflection",
    "response_curve",
    "white_balance",
    "defocus_blur",
    "motion_blur",
    "pose_error",
)
# The world the real photos' scene lives in, and its name.
REAL_SCENE = "ethiopian_head"

# Two pairs per synthetic world: one per-view photometric + one optical, one tone + one
# geometric (each from a different family, so a pair is not two readings of one signal).
DEFAULT_PAIRS = (("exposure", "vignetting"), ("response_curve", "lens_distortion"))


@dataclass(frozen=True)
class Scene:
    """A synthetic scene: config overrides (a nested dict merged into the base config),
    intrinsic effects (always present in its world, part of its truth), the worlds it can be
    rendered in, and its group (scenes sharing a mesh)."""

    name: str
    overrides: dict
    group: str
    intrinsic: tuple[str, ...] = ()
    worlds: tuple[str, ...] = ("own", "mitsuba")
    needs_shared: bool = False


def _mesh_scene(name: str, mesh: str, material: dict, texture: str | None = None) -> Scene:
    shape = {"procedural": None, "mesh_path": str(MESHES / mesh)}
    if texture:
        shape["texture_path"] = str(MESHES / texture)
    return Scene(
        name, {"scene": {"shape": shape, "material": material}}, group=name, needs_shared=True
    )


def _glossy(base: Scene, roughness: float, specular_level: float) -> Scene:
    """base with a permanent specular lobe (path traced: Mitsuba world only)."""
    overrides = copy.deepcopy(base.overrides)
    overrides.setdefault("scene", {}).setdefault("material", {}).update(
        {"roughness": roughness, "specular_level": specular_level}
    )
    overrides["capture"] = {
        "effects": [
            {
                "name": "specular",
                "parameters": {"roughness": roughness, "specular_level": specular_level},
            }
        ]
    }
    return Scene(
        f"{base.name}_glossy",
        overrides,
        group=base.group,
        intrinsic=("specular",),
        worlds=("mitsuba",),
        needs_shared=base.needs_shared,
    )


def _procedural(name: str, shape: str, albedo: str) -> Scene:
    return Scene(
        name, {"scene": {"shape": {"procedural": shape}, "material": {"albedo": albedo}}}, name
    )


_BASE_SCENES = [
    _mesh_scene("spot", "spot_triangulated.obj", {"albedo": "file"}, "spot_texture.png"),
    _mesh_scene("bob", "bob_tri.obj", {"albedo": "file"}),
    _mesh_scene("bunny", "stanford-bunny.obj", {"albedo": "vertex_noise"}),
    _mesh_scene("teapot", "teapot.obj", {"albedo": "vertex_noise"}),
    _procedural("torus", "torus", "checker"),
    _procedural("blob", "blob", "vertex_noise"),
    _procedural("rounded_box", "rounded_box", "vertex_noise"),
]
SCENES: dict[str, Scene] = {scene.name: scene for scene in _BASE_SCENES}
SCENES.update(
    {
        glossy.name: glossy
        for glossy in (
            _glossy(SCENES["spot"], 0.2, 0.8),
            _glossy(SCENES["torus"], 0.25, 0.6),
            _glossy(SCENES["blob"], 0.25, 0.6),
        )
    }
)
DEFAULT_SCENES = ("spot", "bob", "bunny", "teapot", "torus", "spot_glossy", "torus_glossy")


@dataclass(frozen=True)
class BlindCase:
    """One dataset: its world, scene, withheld effects (empty = none withheld) and seed.

    truth: the withheld effects plus the scene's intrinsic ones (a glossy scene's specular):
    what a diagnosis of a diffuse, effect-free fit should name."""

    world: str
    scene: str
    withheld: tuple[str, ...]
    seed: int
    intrinsic: tuple[str, ...] = field(default=())

    @property
    def truth(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(self.intrinsic + self.withheld))

    @property
    def present(self) -> tuple[str, ...]:
        """Effects the world puts in this case without injecting them (PRESENT_IN_WORLD),
        unless they are part of its truth."""
        return tuple(
            name for name in PRESENT_IN_WORLD.get(self.world, ()) if name not in self.truth
        )

    @property
    def label(self) -> str:
        return "+".join(self.withheld) if self.withheld else "none"

    @property
    def kind(self) -> str:
        return {0: "clean", 1: "single"}.get(len(self.truth), "pair")

    @property
    def folder_name(self) -> str:
        return f"{self.world}/{self.scene}/{self.label}_seed{self.seed}"

    def to_json(self) -> dict:
        return {
            "world": self.world,
            "scene": self.scene,
            "withheld": list(self.withheld),
            "seed": self.seed,
            "intrinsic": list(self.intrinsic),
        }


def scene_group(scene: str) -> str:
    """The leave-one-scene-out unit of a scene (glossy variants belong to their mesh's)."""
    return SCENES[scene].group if scene in SCENES else scene


def world_effects(world: str) -> tuple[str, ...]:
    """The single effects a world can make."""
    if world == "own":
        return CAMERA_EFFECTS
    if world == "mitsuba":
        return CAMERA_EFFECTS + LIGHT_TRANSPORT_EFFECTS
    return REAL_EFFECTS


def build_cases(
    worlds: list[str],
    scenes: list[str],
    effects: list[str] | None,
    seeds: list[int],
    pairs: list[tuple[str, str]],
    glossy_effects: list[str] = ("exposure",),
) -> list[BlindCase]:
    """Every case of the benchmark, in a stable order.

    Plain scenes: each world's single effects (restricted to effects when given) for every seed,
    one clean case per seed, and the pairs for every seed (a seed is one draw of every
    effect's strength: docs/decisions/0222-blind-unseen-draws.md). Glossy scenes (Mitsuba only): the
    glossy object alone (truth: specular) and with each of glossy_effects (truth: specular +
    that effect), which is the case built to fool a diagnosis into naming a camera effect.
    The real world gets its injected effects and the untouched photos, whatever scenes says."""
    cases: list[BlindCase] = []
    for world in worlds:
        if world == "real":
            names = [name for name in REAL_EFFECTS if effects is None or name in effects]
            cases += [
                BlindCase(world, REAL_SCENE, (name,), seed) for name in names for seed in seeds
            ]
            cases += [BlindCase(world, REAL_SCENE, (), seed) for seed in seeds]
            continue
        for scene_name in scenes:
            scene = SCENES[scene_name]
            if world not in scene.worlds:
                continue
            if scene.intrinsic:
                extra = [(), *[(name,) for name in glossy_effects]]
                cases += [
                    BlindCase(world, scene_name, withheld, seed, scene.intrinsic)
                    for withheld in extra
                    for seed in seeds
                ]
                continue
            names = [name for name in world_effects(world) if effects is None or name in effects]
            cases += [
                BlindCase(world, scene_name, (name,), seed) for name in names for seed in seeds
            ]
            cases += [BlindCase(world, scene_name, (), seed) for seed in seeds]
            cases += [
                BlindCase(world, scene_name, tuple(pair), seed) for pair in pairs for seed in seeds
            ]
    return cases


def merge(base: dict, overrides: dict) -> dict:
    """base with overrides merged in (nested dicts merged, everything else replaced)."""
    merged = copy.deepcopy(base)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def case_config(base: dict, case: BlindCase) -> dict:
    """The synthetic case's run config as a dict: the base config, the scene, the world's
    backend, the case's seed, synth and fit stages only."""
    scene = SCENES[case.scene]
    config = merge(base, scene.overrides)
    backend = {"own": "own", "mitsuba": "mitsuba"}[case.world]
    config = merge(config, {"capture": {"backend": backend}})
    config["seed"] = case.seed
    config["stages"] = ["synth", "fit"]
    return config


def missing_inputs(scene: str) -> str | None:
    """Why a scene cannot run here (its meshes are absent), or None."""
    if scene == REAL_SCENE:
        return None if (SHARED / "captures" / REAL_SCENE).is_dir() else "../shared/captures absent"
    if SCENES[scene].needs_shared and not MESHES.is_dir():
        return "../shared/meshes absent"
    return None


def interleaved(cases: list[BlindCase]) -> list[BlindCase]:
    """cases reordered so that an interrupted run has scored something of everything: clean
    cases first (calibration needs them in every scene group), then rounds: in round k every
    effect (and every pair) runs on the k-th scene of its own rotation of the scenes (so each
    round spreads the effects over all scenes), in both synthetic worlds and the real one."""
    effects = list(EFFECT_ORDER)
    pairs = list(dict.fromkeys(case.withheld for case in cases if len(case.withheld) > 1))
    synthetic = list(
        dict.fromkeys(scene_group(case.scene) for case in cases if case.world != "real")
    )
    scenes = [*synthetic, REAL_SCENE]
    world_order = {name: rank for rank, name in enumerate(WORLDS)}

    def key(case: BlindCase) -> tuple:
        if not case.withheld and not case.intrinsic:
            return (
                0,
                0,
                0,
                case.seed,
                scenes.index(scene_group(case.scene)),
                world_order[case.world],
            )
        if len(case.withheld) > 1:
            rank = len(effects) + pairs.index(case.withheld)
        elif case.withheld:
            rank = effects.index(case.withheld[0])
        else:
            rank = -1  # a glossy object alone: the case built to fool the diagnosis
        # The real world has one scene: its few cases all go in the first round.
        rotation = (
            0
            if case.world == "real"
            else (synthetic.index(scene_group(case.scene)) - max(rank, 0)) % len(synthetic)
        )
        return (
            1 + rotation,
            case.seed,
            rank,
            0,
            scenes.index(scene_group(case.scene)),
            world_order[case.world],
        )

    return sorted(cases, key=key)
