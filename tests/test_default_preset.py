"""Every command and module falls back on the same preset (DEFAULT_PRESET) when given neither a preset nor counts;
``torch-ao fit``'s default pipeline is fitted at longer steps (``very_high``)."""
import pytest

from torch_ao.bench import DEFAULT, QUICK
from torch_ao.cli import build_parser
from torch_ao.methods import DEFAULT_PRESET, METHODS, PRESETS, get_method
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
    default variant, back-face thickness), which is fitted at ``very_high``: 2 slices x 7 steps, chosen leave one
    scene out on the fit set (docs/accuracy.md); the rows it is compared with stay at the default preset."""
    from torch_ao.commands.fit import DEFAULT_PIPELINE_PRESET, _chosen_preset

    args = _subparser("fit").parse_args([])
    assert args.preset is None
    args.thickness = "backface"
    assert _chosen_preset(args) == DEFAULT_PIPELINE_PRESET == "very_high"
    assert PRESETS["very_high"] == (2, 7) and PRESETS["high_steps"] == (2, 5)
    for flags, thickness in ((["--method", "gtao"], "scalar"), (["--variant", "exact"], "backface"), ([], "scalar")):
        args = _subparser("fit").parse_args(flags)
        args.thickness = thickness
        assert _chosen_preset(args) == DEFAULT_PRESET


def test_ao_command_default_runs_the_default_preset():
    from torch_ao.commands.ao import build_method

    args = _subparser("ao").parse_args([])
    m = build_method(args.method, args)
    assert (m.slices, m.steps) == PRESETS[DEFAULT_PRESET]


def test_bench_presets_include_the_default():
    assert DEFAULT_PRESET in DEFAULT.presets and DEFAULT_PRESET in QUICK.presets
