"""Bad input on the command line: one clear line naming the argument, exit status 2, no traceback,
and no output file written."""
import argparse

import numpy as np
import pytest

from torch_ao.cli import main


@pytest.fixture
def files(tmp_path):
    np.savez(tmp_path / "ok.npz", depth=np.full((6, 8), 2.0, np.float32), fov_y_degrees=60.0)
    np.savez(tmp_path / "pickled.npz", depth=np.array([{"x": 1}], dtype=object))
    (tmp_path / "junk.npz").write_bytes(b"garbage")
    np.savez(tmp_path / "negative.npz", depth=-np.ones((6, 8), np.float32), fov_y_degrees=60.0)
    np.savez(tmp_path / "badK.npz", depth=np.ones((6, 8), np.float32), intrinsics=np.eye(3) * [0, 1, 1])
    np.savez(tmp_path / "nancam.npz", depth=np.ones((6, 8), np.float32), intrinsics=np.full((3, 3), np.nan))
    np.savez(tmp_path / "badnormal.npz", depth=np.ones((6, 8), np.float32), fov_y_degrees=60.0, normal=np.ones((6, 8, 2), np.float32))
    np.savez(tmp_path / "badfov.npz", depth=np.ones((6, 8), np.float32), fov_y_degrees=0.0)
    np.savez(tmp_path / "noref.npz", depth=np.ones((6, 8), np.float32), fov_y_degrees=60.0)
    ao = np.ones((6, 8), np.float32)
    ao[2, 2] = np.nan
    np.savez(tmp_path / "nanref.npz", depth=np.ones((6, 8), np.float32), fov_y_degrees=60.0, ao=ao)
    return tmp_path


CASES = [
    (["ao", "{d}/missing.npz"], "path: no such file"),
    (["ao", "{d}/pickled.npz"], "pickled"),
    (["ao", "{d}/junk.npz"], "not a valid .npz"),
    (["ao", "{d}/negative.npz"], "depth: negative"),
    (["ao", "{d}/badK.npz"], "intrinsics: focal"),
    (["ao", "{d}/nancam.npz"], "intrinsics: every entry must be finite"),
    (["ao", "{d}/badnormal.npz"], "normal"),
    (["ao", "{d}/badfov.npz"], "fov_y_degrees"),
    (["ao", "{d}/ok.npz", "--method", "nope"], "--method: unknown method"),
    (["ao", "{d}/ok.npz", "--method", "gtao", "--slices", "0"], "slices"),
    (["ao", "{d}/ok.npz", "--method", "gtao", "--radius", "-1"], "radius"),
    (["ao", "{d}/ok.npz", "--method", "gtao", "--radius", "nan"], "radius"),
    (["ao", "{d}/ok.npz", "--method", "gtao", "--device", "cuda:7"], "--device"),
    (["ao", "{d}/ok.npz", "--method", "gtao", "--rounding", "ceil"], "--rounding: not an option"),
    (["fit", "--reference", "{d}/noref.npz", "--steps", "1"], "has no 'ao' array"),
    (["fit", "--reference", "{d}/nanref.npz", "--steps", "1"], "ao: 1 non-finite"),
    (["fit", "--method", "nope"], "--method: unknown method"),
    (["fit", "--size", "big", "--steps", "1"], "--size"),
    (["fit", "--scenes", "atlantis", "--steps", "1"], "--scenes: unknown scene"),
    (["fit", "--reference", "{d}/ok.npz", "--steps", "-1"], "--steps"),
    (["ao", "{d}/ok.npz", "--tau", "abc"], "argument --tau: expected a number"),
    (["ao", "{d}/ok.npz", "--slices", "2.5"], "argument --slices: expected an integer"),
    (["ao", "{d}/ok.npz", "--method", "bitmask", "--mode", "bogus"], "--mode"),
    (["ao", "{d}/ok.npz", "--method", "pssao", "--jitter"], "--jitter: not an option of method 'pssao'"),
    (["ao", "{d}/ok.npz", "--tolerance", "-1", "--auto"], "argument --tolerance: expected a number >= 0"),
    (["ao", "{d}/ok.npz", "--bogus-flag", "1"], "unrecognized arguments: --bogus-flag"),
    (["bench", "--repeats", "0"], "argument --repeats: expected an integer >= 1"),
    (["bench", "--threads", "0"], "argument --threads: expected an integer >= 1"),
    (["bench", "--max-distance", "0"], "argument --max-distance: expected a number > 0"),
    (["bench", "--methods", "gtao", "--tau", "0.5"], "--tau: not an option of any swept method"),
]


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(c[0][:2]) + f"-{i}" for i, c in enumerate(CASES)])
def test_cli_bad_input(files, capsys, argv, message):
    out = files / "out"
    argv = [a.format(d=files) for a in argv] + (["--out", str(out / "result.npz")] if argv[0] == "ao" else ["--out", str(out)])
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert message in err[0]
    assert not (out / "result.npz").exists() and not (out / "params.json").exists()


# ------------------------------------------------------------------------------------------ --help
def _squash(text: str) -> str:
    return " ".join(text.split())


def _subparser(name: str):
    from torch_ao.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices[name]


def _flag_help(parser, flag: str) -> str:
    action = next(a for a in parser._actions if flag in a.option_strings)
    return _squash(action.help or "")


def test_ao_help_names_unit_range_and_default(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["ao", "--help"])
    assert exit_.value.code == 0
    text = _squash(capsys.readouterr().out)
    tau = _flag_help(_subparser("ao"), "--tau")
    assert "Unit: sectors." in tau and "Default: 0.25." in tau and tau in text
    radius = _flag_help(_subparser("ao"), "--radius")
    assert "Unit: world units." in radius and "Default: 1.0." in radius
    tolerance = _flag_help(_subparser("ao"), "--tolerance")
    assert "Range: [0, inf)." in tolerance and "Default: None." in tolerance and tolerance in text
    method = _flag_help(_subparser("ao"), "--method")
    assert "One of: ssao, hbao, ue4_ssao, gtao, pssao, bitmask, ssilvb." in method and "Default: gtao." in method
    assert "method parameter" not in text and "world units where lengths" not in text


def test_every_method_flag_help_is_its_options_description():
    """Each method's own Option.describe() is in the help of its flag (one source of truth), and
    every flag of ao and bench has help text beyond its name."""
    from torch_ao.commands.options_cli import FLAG_KINDS, flag
    from torch_ao.methods import METHODS, get_method

    ao, bench = _subparser("ao"), _subparser("bench")
    for name in METHODS:
        for opt_name, opt in get_method(name).options().items():
            if opt.kind not in FLAG_KINDS:
                continue
            assert _squash(opt.describe()) in _flag_help(ao, flag(opt_name)), (name, opt_name)
    for parser in (ao, bench):
        for action in parser._actions:
            if action.option_strings and action.dest != "help" and action.help is not argparse.SUPPRESS:  # hidden aliases: test_cli_help
                assert len(action.help or "") > len(action.dest) + 10, action.option_strings


def test_option_flags_builder():
    """An Option becomes a flag with its type, choices, bounds and help; only given flags come back."""
    import argparse

    from torch_ao.cli import _Parser
    from torch_ao.commands.options_cli import add_options, given
    from torch_ao.options import Option

    opts = {"width_px": Option("width_px", 4, "a width", int, unit="pixels", minimum=1, maximum=8),
            "kind": Option("kind", "a", "a kind", str, choices=("a", "b")),
            "soft": Option("soft", False, "soft or not", bool)}
    p = _Parser(prog="t")
    names = add_options(p, opts)
    assert names == ["width_px", "kind", "soft"]
    args = p.parse_args(["--width-px", "8", "--no-soft"])
    assert given(args, names) == {"width_px": 8, "soft": False}
    assert given(p.parse_args([]), names) == {}
    for argv, message in ((["--width-px", "9"], "argument --width-px: expected an integer <= 8"),
                          (["--width-px", "x"], "argument --width-px: expected an integer"),
                          (["--kind", "c"], "argument --kind: unknown kind 'c'; expected one of a, b")):
        with pytest.raises(Exception, match=message):
            p.parse_args(argv)
    help_ = _squash(p.format_help())
    assert "a width. Unit: pixels. Range: [1, 8]. Default: 4." in help_
    assert "a kind. One of: a, b. Default: a." in help_ and "--soft, --no-soft" in help_
    q = argparse.ArgumentParser()
    add_options(q, opts, given_only=False)
    assert vars(q.parse_args([])) == {"width_px": 4, "kind": "a", "soft": False}


def test_ao_flags_only_given_arguments_reach_the_constructor():
    """A flag not given leaves the constructor's default (here GTAO's per-variant fetch/border)."""
    from torch_ao.cli import build_parser
    from torch_ao.commands.ao import build_method
    from torch_ao.methods import get_method

    args = build_parser().parse_args(["ao", "--method", "gtao", "--variant", "hdrp", "--radius", "0.5", "--no-jitter"])
    m = build_method("gtao", args)
    ref = get_method("gtao")(variant="hdrp", radius=0.5, jitter=False)
    assert float(m.radius.detach()) == 0.5 and m.jitter is False
    assert (m.fetch, m.border, m.azimuth, m.normalize) == (ref.fetch, ref.border, ref.azimuth, ref.normalize) == (
        "nearest", "clamp", "screen", "none")
    assert (m.slices, m.steps) == (ref.slices, ref.steps)


def test_bench_method_flags_apply_to_the_methods_that_take_them():
    from torch_ao.commands.bench import _method_params
    from torch_ao.methods import get_method

    methods = {"gtao": get_method("gtao"), "bitmask": get_method("bitmask")}
    assert _method_params(methods, {"thickness": 0.3}, {}) == {"bitmask": {"thickness": 0.3}}
    assert _method_params(methods, {"thickness": 0.3, "final_power": 2.0}, {"bitmask": {"thickness": 0.7}}) == {
        "gtao": {"final_power": 2.0}, "bitmask": {"thickness": 0.7}}
