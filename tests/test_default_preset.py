"""Every command and module falls back on the same preset (DEFAULT_PRESET) when given neither a preset nor counts;
``torch-ao fit``'s default pipeline is fitted at longer steps (``very_high_steps``), staggered, along screen
directions."""
import pytest

from torch_ao.bench import DEFAULT, QUICK
from torch_ao.cli import build_parser
from torch_ao.methods import DEFAULT_PRESET, PRESETS, get_method
from torch_ao.methods.common import Sampling


def _subparser(name):
    parser = build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices[name]


@pytest.mark.parametrize("name", ["gtao", "bitmask"])
def test_modules_default_to_the_default_preset(name):
    m = get_method(name)()
    assert (m.slices, m.steps) == PRESETS[DEFAULT_PRESET]


def test_sampling_dataclass_default():
    s = Sampling()
    assert (s.slices, s.steps) == PRESETS[DEFAULT_PRESET]


def test_fit_command_default_preset():
    """``torch-ao fit`` without ``--preset``: the default preset for every pipeline but its default one (bitmask,
    default variant, back-face thickness), which is fitted at ``very_high_steps``: 2 slices x 8 steps, staggered,
    slices spaced on screen, chosen leave one scene out on the fit set (docs/accuracy.md); the rows it is compared
    with stay at the default preset and the method's own sampling."""
    from torch_ao.commands.fit import DEFAULT_PIPELINE_PRESET, _chosen_preset, pipeline_options

    args = _subparser("fit").parse_args([])
    assert args.preset is None
    args.thickness = "backface"
    assert _chosen_preset(args) == DEFAULT_PIPELINE_PRESET == "very_high_steps"
    assert PRESETS["very_high_steps"] == (2, 8) and PRESETS["very_high"] == (2, 7) and PRESETS["high_steps"] == (2, 5)
    args.preset = _chosen_preset(args)
    options = pipeline_options(args, 1.0)
    assert (options["preset"], options["stagger"], options["azimuth"], options["fetch"]) == (
        "very_high_steps", True, "screen", "edge_aware")
    m = get_method("bitmask")(**options)
    assert (m.slices, m.steps) == (2, 8)
    for flags, thickness in ((["--method", "gtao"], "scalar"), (["--variant", "exact"], "backface"), ([], "scalar")):
        args = _subparser("fit").parse_args(flags)
        args.thickness = thickness
        assert _chosen_preset(args) == DEFAULT_PRESET
        args.preset = _chosen_preset(args)
        assert "stagger" not in pipeline_options(args, 1.0) and "azimuth" not in pipeline_options(args, 1.0)
    args = _subparser("fit").parse_args(["--no-stagger", "--azimuth", "view", "--preset", "high"])
    args.thickness = "backface"  # (the flags win over the default pipeline's sampling)
    assert {k: pipeline_options(args, 1.0)[k] for k in ("preset", "stagger", "azimuth")} == {
        "preset": "high", "stagger": False, "azimuth": "view"}
    args = _subparser("fit").parse_args(["--method", "gtao", "--stagger", "--azimuth", "screen"])
    args.thickness, args.preset = "scalar", "high"
    assert get_method("gtao")(**pipeline_options(args, 1.0)).stagger is True


def test_ao_command_default_runs_the_default_preset():
    from torch_ao.commands.ao import build_method

    args = _subparser("ao").parse_args([])
    m = build_method(args.method, args)
    assert (m.slices, m.steps) == PRESETS[DEFAULT_PRESET]


def test_bench_presets_include_the_default():
    assert DEFAULT_PRESET in DEFAULT.presets and DEFAULT_PRESET in QUICK.presets
