"""``nimbus-synth degrade``: turn a clean scene into a weather benchmark (one scene folder per setting)."""

from __future__ import annotations

import argparse
from dataclasses import replace

from nimbus.cli_util import MAX_SEED, seed_arg
from nimbus.config_set import apply_overrides, parse_set_args
from nimbus.config_validation import field_problem
from nimbus.errors import NimbusError
from weather_synth.config import PROTOCOL_SUMMARIES, PROTOCOLS, SynthConfig, protocol_config
from weather_synth.compose import COMPOSITION_ORDERS
from weather_synth.haze import HAZE_MODES
from weather_synth.rain import RAIN_PRESETS, rain_preset
from weather_synth.settings import ALL_SETTING_NAMES, parse_weather
from weather_synth.snow import SNOW_PRESETS, snow_preset

HELP = "degrade a scene with haze, rain, snow and their mixes into a benchmark dataset (one scene per setting)"
EXAMPLE = "nimbus-synth degrade scenes/garden --out bench/garden --weather all --seed 0"


def add_synth_arguments(parser: argparse.ArgumentParser) -> None:
    """The weather options shared by ``degrade`` and ``demo``."""
    g = parser.add_argument_group("weather")
    g.add_argument("--weather", default="all",
                   help=f"settings, comma-separated: H|haze, R|rain, S|snow joined by '+', or 'all' "
                        f"({','.join(ALL_SETTING_NAMES)}); case-insensitive")
    g.add_argument("--protocol", choices=PROTOCOLS, default="onerestore",
                   help="; ".join(f"{name}: {what}" for name, what in PROTOCOL_SUMMARIES.items()))
    g.add_argument("--seed", type=seed_arg, default=0, help=f"scene seed in [0, {MAX_SEED}]: same seed, same bytes")
    g.add_argument("--depth", default="auto", metavar="SOURCE",
                   help="depth for haze and depth-aware particles: scene (the views' depth maps), recon (a quick "
                        "3DGS fit to the views, rendered per view: consistent across views), sparse (densified SfM "
                        "points, view by view), onnx:MODEL.onnx (monocular model aligned to the points), auto "
                        "(scene if every view has a depth map, else onnx with --depth-model, else recon; says "
                        "which it picked)")
    g.add_argument("--depth-model", default=None, metavar="MODEL.onnx",
                   help="ONNX depth model that --depth auto uses for a scene without depth maps")
    g.add_argument("--depth-cache", default=None, metavar="DIR|none",
                   help="where --depth recon keeps its fits, so a second degrade of the scene reuses them "
                        "(default: $NIMBUS_CACHE/depth, else ~/.cache/nimbus/depth; 'none': no cache)")
    h = parser.add_argument_group("haze")
    h.add_argument("--haze-mode", choices=HAZE_MODES, default=None,
                   help="override the protocol's haze model (heterogeneous: world-space height fog with 3D noise)")
    h.add_argument("--beta", default=None, metavar="B|LO:HI",
                   help="extinction: a fixed value or a range to sample (onerestore: per unit of normalised "
                        "depth, default 1:2; physical: 1 / scene unit)")
    h.add_argument("--visibility", type=float, default=None, metavar="V",
                   help="physical haze: visibility distance in scene units (beta = 3.912 / V); "
                        "default 5 x the median surface distance")
    h.add_argument("--airlight", default=None, metavar="A|R,G,B|LO:HI",
                   help="airlight in [0, 1]: grey value, RGB tint, or grey range to sample (default 0.6:0.9)")
    p = parser.add_argument_group("particles")
    p.add_argument("--rain", default="medium", metavar="PRESET|AMOUNT",
                   help=f"rain intensity: {'|'.join(RAIN_PRESETS)} or a number scaling the medium "
                        "streak brightness (0 = none)")
    p.add_argument("--snow", default="medium", metavar="PRESET|AMOUNT",
                   help=f"snow intensity: {'|'.join(SNOW_PRESETS)} or a number scaling the medium flake count "
                        "(0 = none)")
    p.add_argument("--depth-aware", action=argparse.BooleanOptionalAction, default=None,
                   help="particles get depths: size ~ 1/z, hidden behind nearer surfaces (physical default)")
    c = parser.add_argument_group("compositing")
    c.add_argument("--order", choices=COMPOSITION_ORDERS, default=None,
                   help="onerestore: rain -> snow -> haze (particles behind the haze); physical: each particle "
                        "attenuated over its own distance")
    c.add_argument("--linear", action=argparse.BooleanOptionalAction, default=None,
                   help="composite in linear light (sRGB decoded) instead of display values")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="any other config value, e.g. --set haze.fog_noise_amplitude=0.3 --set rain.slices=3 "
                             "(repeatable; keys as in the manifest's config)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _float(text: str, what: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise NimbusError(f"{what}: {text!r} is not a number") from None


def _range(text: str, what: str) -> tuple[float, float] | None:
    """``LO:HI`` as two numbers (a range to sample); None when ``text`` is one value."""
    if ":" not in text:
        return None
    lo, hi = (_float(x, what) for x in text.split(":", 1))
    return lo, hi


def _intensity(text: str, preset, what: str):
    try:
        amount = float(text)
    except ValueError:
        return preset(text)
    config = preset("medium")
    problem = field_problem(type(config), "amount", amount, type(config).LIMITS)
    if problem:
        raise NimbusError(f"--{what} {text}: the amount {problem}")
    return replace(config, amount=amount)


def config_from_args(args: argparse.Namespace, scene=None) -> SynthConfig:
    """The SynthConfig the weather options describe (``scene`` is not used: ``auto`` is resolved on use)."""
    cfg = protocol_config(args.protocol, seed=args.seed)
    haze = cfg.haze
    if args.haze_mode is not None:
        haze = replace(haze, mode=args.haze_mode)
    if args.beta is not None:
        span = _range(args.beta, "--beta")
        haze = replace(haze, beta=None, beta_range=span) if span else replace(haze, beta=_float(args.beta, "--beta"))
    if args.visibility is not None:
        haze = replace(haze, visibility=args.visibility)
    if args.airlight is not None:
        span = _range(args.airlight, "--airlight")
        if span:
            haze = replace(haze, airlight=None, airlight_range=span)
        else:
            vals = [_float(x, "--airlight") for x in args.airlight.split(",")]
            if len(vals) not in (1, 3):
                raise NimbusError(f"--airlight takes one grey value or R,G,B, got {args.airlight!r}")
            haze = replace(haze, airlight=tuple(vals * 3 if len(vals) == 1 else vals))
    rain = _intensity(args.rain, rain_preset, "rain")
    snow = _intensity(args.snow, snow_preset, "snow")
    compose = cfg.compose
    if args.order is not None:
        compose = replace(compose, order=args.order)
    if args.linear is not None:
        compose = replace(compose, linear=args.linear)
    # auto is resolved by the depth source (weather_synth.depth.pick_depth_source), which says what it picked.
    depth = replace(cfg.depth, source=args.depth, model=getattr(args, "depth_model", None) or "",
                    recon_cache=getattr(args, "depth_cache", None) or "")
    cfg = replace(cfg, haze=haze, rain=rain, snow=snow, compose=compose, depth=depth,
                  depth_aware=cfg.depth_aware if args.depth_aware is None else args.depth_aware)
    return apply_overrides(cfg, parse_set_args(args.set))


BUILTIN_PREFIX = "builtin:"


def load_input_scene(spec: str, downscale: int = 1):
    """A scene folder, or ``builtin:NAME[:SIZE]`` for a built-in scene rendered in memory.

    ``downscale`` picks a scene folder's ``images_<d>/``; a built-in scene has no
    such copies (its SIZE sets the resolution), so anything but 1 is refused
    rather than ignored and then recorded as if it had been applied.
    """
    if spec.startswith(BUILTIN_PREFIX):
        from nimbus.data.builtin import SIZES, list_scenes, render_builtin

        parts = spec.split(":")
        if len(parts) > 3 or not parts[1]:
            raise NimbusError(f"{spec!r}: write a built-in scene as builtin:NAME[:SIZE], e.g. builtin:garden:small "
                              f"(scenes: {', '.join(list_scenes())}; sizes: {', '.join(SIZES)})")
        name, size = parts[1], parts[2] if len(parts) > 2 else "tiny"
        if downscale != 1:
            raise NimbusError(f"--downscale {downscale} applies to scene folders with images_{downscale}/; a built-in "
                              f"scene's resolution is its SIZE: use builtin:{name}:tiny|compact|small|standard "
                              "without --downscale")
        return render_builtin(name, size)
    from nimbus.data.io import load_scene

    return load_scene(spec, downscale=downscale)


def input_paths(spec: str) -> list[str]:
    """The paths a SCENE argument reads (none for a built-in scene)."""
    return [] if spec.startswith(BUILTIN_PREFIX) else [spec]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE",
                        help="scene folder (COLMAP images/ + sparse/0, or transforms.json), "
                             "or builtin:NAME[:SIZE] (e.g. builtin:garden:small)")
    parser.add_argument("--out", required=True, metavar="OUT", help="dataset folder to create (one subfolder per setting)")
    parser.add_argument("--overwrite", action="store_true", help="write into a non-empty OUT, replacing its settings")
    parser.add_argument("--downscale", type=int, default=1, help="use images_<d>/ of a Mip-NeRF360-style scene")
    add_synth_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from weather_synth.dataset import check_dataset_out, degrade_scene, format_summary

    settings = parse_weather(args.weather)
    # Before loading: fail fast.  degrade_scene checks again against every file the scene reads.
    check_dataset_out(args.out, args.overwrite, inputs=input_paths(args.scene))
    scene = load_input_scene(args.scene, args.downscale)
    config = config_from_args(args, scene)
    summaries = degrade_scene(scene, args.out, settings, config, overwrite=args.overwrite,
                              progress=not args.quiet, source=args.scene)
    print(format_summary(summaries))
    print(f"wrote {args.out} ({len(summaries)} settings x {len(scene.views)} views)")
    return 0
