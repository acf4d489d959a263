"""Every flag of every ``torch-ao`` subcommand (read from the real parser): its help says what it does
and its default (or that it is a switch); a number flag is built from an :class:`~torch_ao.options.Option`
and states its unit and range; a value outside the range exits 2 with one line naming the flag."""
import argparse
import math
import re

import pytest

from torch_ao.cli import build_parser, main
from torch_ao.options import Option

SWITCHES = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse.BooleanOptionalAction)


def _squash(text: str) -> str:
    return " ".join(text.split())


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


SUBCOMMANDS = _subcommands()
FLAGS = [(name, action) for name, p in SUBCOMMANDS.items() for action in p._actions
         if action.option_strings and not isinstance(action, argparse._HelpAction) and action.help is not argparse.SUPPRESS]
#: Older spellings kept working but not shown in --help.
HIDDEN = [(name, action) for name, p in SUBCOMMANDS.items() for action in p._actions
          if action.option_strings and action.help is argparse.SUPPRESS]
IDS = [f"{name} {action.option_strings[-1]}" for name, action in FLAGS]


def _options(action) -> dict[str, Option]:
    """``{owner: Option}`` the flag was built from (``{}`` for a hand-written flag)."""
    return getattr(action.type, "options", {})


def _bad_value(opt: Option) -> str | None:
    """A value just outside ``opt``'s range (``None`` when it has none)."""
    if opt.minimum is not None:
        bad = opt.minimum if opt.open_minimum else opt.minimum - 1
    elif opt.maximum is not None:
        bad = opt.maximum if opt.open_maximum else opt.maximum + 1
    else:
        return None
    return str(int(bad)) if opt.kind is int else repr(float(bad))


def test_every_subcommand_is_covered():
    assert set(SUBCOMMANDS) == {"ao", "render", "fit", "bench", "convert", "export"}
    for name, parser in SUBCOMMANDS.items():
        assert sum(1 for n, _ in FLAGS if n == name) >= 3, name


def test_hidden_flags_are_aliases_of_shown_ones():
    assert sorted(a.option_strings[0] for n, a in HIDDEN) == ["--no-quiet"] * 4 + ["--quiet"] * 4
    for command, action in HIDDEN:
        assert any(a.dest == action.dest for n, a in FLAGS if n == command), action.option_strings


@pytest.mark.parametrize("command", ["ao", "render", "fit", "bench"])
def test_progress_flag_is_spelled_the_same_on_every_command(command):
    parser = build_parser()
    rest = ["--out", "x"]
    assert parser.parse_args([command, *rest]).progress is True
    assert parser.parse_args([command, "--no-progress", *rest]).progress is False
    assert parser.parse_args([command, "--no-progress", "--progress", *rest]).progress is True
    assert parser.parse_args([command, "--quiet", *rest]).progress is False  # the older spelling
    assert parser.parse_args([command, "--quiet", "--no-quiet", *rest]).progress is True
    assert "--progress, --no-progress" in SUBCOMMANDS[command].format_help()
    assert "--quiet" not in SUBCOMMANDS[command].format_help()


@pytest.mark.parametrize("command, action", FLAGS, ids=IDS)
def test_flag_help_says_what_and_default(command, action):
    help_ = _squash(action.help or "")
    assert action.help is not argparse.SUPPRESS
    assert len(help_) > len(action.dest) + 10, help_
    # the default is said once, by the help itself (no formatter adding "(default: None)")
    assert not issubclass(SUBCOMMANDS[command].formatter_class, argparse.ArgumentDefaultsHelpFormatter)
    assert "(default: None)" not in help_ and "%(default)" not in help_
    if not isinstance(action, SWITCHES):
        assert re.search(r"\bDefault: \S", help_) or "(required)" in help_, help_
    # --help prints it (argparse wraps lines, also after hyphens and inside long words: compare without spaces)
    assert "".join(help_.replace("%%", "%").split()) in "".join(SUBCOMMANDS[command].format_help().split())


@pytest.mark.parametrize("command, action", FLAGS, ids=IDS)
def test_number_flags_come_from_options_with_unit_and_range(command, action):
    assert action.type not in (int, float), "a hand-written number flag: build it from an Option"
    help_ = _squash(action.help or "")
    for opt in _options(action).values():
        assert _squash(opt.describe()) in help_
        if opt.unit:
            assert f"Unit: {opt.unit}." in help_
        if opt.minimum is not None or opt.maximum is not None:
            assert "Range: " in help_
        if opt.choices:
            assert "One of: " + ", ".join(map(str, opt.choices)) + "." in help_


BOUNDED = [(name, action, owner, opt) for name, action in FLAGS
           for owner, opt in _options(action).items() if _bad_value(opt) is not None]


def _dedupe(cases):
    seen, out = set(), []
    for name, action, owner, opt in cases:
        one = len(set(_options(action).values())) == 1
        key = (name, action.dest, None if one else opt)
        if key not in seen:
            seen.add(key)
            out.append((name, action, owner if not one else "", opt))
    return out


BOUNDED = _dedupe(BOUNDED)


@pytest.mark.parametrize("command, action, owner, opt", BOUNDED,
                         ids=[f"{c} {a.option_strings[-1]} {o}".strip() for c, a, o, _ in BOUNDED])
def test_bad_value_of_a_bounded_flag_exits_2_naming_it(command, action, owner, opt, tmp_path, capsys):
    flag = action.option_strings[-1]
    argv = [command]
    if owner:  # each method checks its own bounds: choose that method
        argv += ["--method" if command == "ao" else "--methods", owner]
    argv += [f"{flag}={_bad_value(opt)}", "--out", str(tmp_path / ("out.npz" if command in ("ao", "render", "convert") else "out"))]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert flag in err[0], err[0]
    assert list(tmp_path.iterdir()) == []


def test_render_flags_are_its_options_with_the_same_defaults_and_parsing():
    from torch_ao.commands.render import OPTIONS

    parser = SUBCOMMANDS["render"]
    for opt in OPTIONS:
        action = next(a for a in parser._actions if a.dest == opt.name)
        assert _squash(opt.describe()) in _squash(action.help), opt.name
    args = build_parser().parse_args(["render", "stairs"])
    assert (args.width, args.height, args.spp, args.max_distance, args.seed, args.chunk_rays) == (
        None, None, 256, math.inf, 0, 262144)  # the size: a scene file's film, else 320x180
    assert (args.mesh, args.mesh_backend, args.device, args.ground_plane, args.fov, args.out) == (
        [], "auto", "cpu", None, None, None)
    assert (args.list, args.indirect, args.no_uniform, args.backface, args.mesh_normalize) == (False,) * 5
    assert args.progress is True
    args = build_parser().parse_args(["render", "--mesh", "a.obj", "--mesh", "b.ply", "--eye", "-2,1,3",
                                      "--ground-plane", "--max-distance", "inf", "--fov", "45"])
    assert (args.mesh, args.eye, args.ground_plane, args.max_distance, args.fov) == (
        ["a.obj", "b.ply"], "-2,1,3", "auto", math.inf, 45.0)
    assert build_parser().parse_args(["render", "--ground-plane", "-0.5"]).ground_plane == -0.5
    assert build_parser().parse_args(["render", "--up=-0,-1,0"]).up == "-0,-1,0"


def test_fit_flags_are_its_options_with_the_same_defaults():
    from torch_ao.commands.fit import OPTIONS
    from torch_ao.fit import FitConfig

    parser = SUBCOMMANDS["fit"]
    for opt in OPTIONS:
        action = next(a for a in parser._actions if a.dest == opt.name)
        assert _squash(opt.describe()) in _squash(action.help), opt.name
    args = build_parser().parse_args(["fit"])
    assert (args.method, args.preset, args.weighting, args.loss, args.size, args.out, args.device) == (
        "bitmask", None, "cosine", "l1", "160x96", "fit-out", "cpu")  # (preset: chosen with the pipeline)
    assert (args.steps, args.lr, args.hard_every, args.hard_patience, args.batch_views, args.seed) == (
        60, 0.05, 10, 2, 0, 0)
    assert (args.lr, args.hard_every, args.batch_views, args.seed, args.loss) == (
        FitConfig.lr, FitConfig.hard_every, FitConfig.batch_views, FitConfig.seed, FitConfig.loss)
    assert (args.spp, args.max_distance, args.train_views) == (256, 1.0, 2)
    assert (args.reference, args.holdout, args.variant, args.radius, args.params, args.init, args.cache) == (None,) * 7
    assert (args.no_denoise, args.progress) == (False, True)
    args = build_parser().parse_args(["fit", "--reference", "a.npz", "b.npz", "--loss", "mse", "--no-denoise"])
    assert (args.reference, args.loss, args.no_denoise) == (["a.npz", "b.npz"], "mse", True)


@pytest.mark.parametrize("argv, message", [
    (["fit", "--max-distance", "inf"], "argument --max-distance: expected a finite number"),
    (["fit", "--loss", "l2"], "argument --loss: unknown loss 'l2'; expected one of l1, mse"),
    (["fit", "--method", "nope"], "argument --method: unknown method 'nope'"),
    (["render", "--fov", "180"], "argument --fov: expected a number < 180"),
    (["render", "--mesh-backend", "optix"], "argument --mesh-backend: unknown mesh_backend 'optix'"),
    (["render", "--spp", "1"], "argument --spp: expected an integer >= 2"),
    (["convert", "in.exr", "--far", "0"], "argument --far: expected a number > 0"),
])
def test_bad_values_message(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_convert_far_takes_inf():
    assert build_parser().parse_args(["convert", "in.exr", "--far", "inf"]).far == math.inf
    assert build_parser().parse_args(["convert", "in.exr"]).far is None


def test_every_cited_document_exists():
    """``docs/X.md`` named in --help, in the library's source or in the docs, and every relative
    markdown link of README.md and docs/, point to files that exist."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    texts = {f"{name} --help": p.format_help() for name, p in SUBCOMMANDS.items()}
    texts |= {str(p.relative_to(root)): p.read_text() for p in (root / "torch_ao").rglob("*.py")}
    markdown = [root / "README.md", *sorted((root / "docs").glob("*.md"))]
    texts |= {str(p.relative_to(root)): p.read_text() for p in markdown}
    cited = {(where, name) for where, text in texts.items() for name in re.findall(r"docs/[\w./-]+?\.md", _squash(text))}
    assert ("ao --help", "docs/gbuffer.md") in cited
    missing = [(where, name) for where, name in cited if not (root / name).is_file()]
    for page in markdown:
        for link in re.findall(r"\]\(([^)#:\s]+)(?:#[^)]*)?\)", page.read_text()):
            if not (page.parent / link).exists():
                missing.append((page.name, link))
    assert missing == []


def test_version(capsys):
    import torch_ao

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"torch-ao {torch_ao.__version__}\n"


def test_python_m_torch_ao_is_the_command_line():
    import subprocess
    import sys
    from pathlib import Path

    import torch_ao

    root = Path(__file__).resolve().parent.parent
    env = {"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"}
    ok = subprocess.run([sys.executable, "-m", "torch_ao", "--version"], capture_output=True, text=True, env=env)
    assert (ok.returncode, ok.stdout) == (0, f"torch-ao {torch_ao.__version__}\n")
    bad = subprocess.run([sys.executable, "-m", "torch_ao", "ao", "--slices", "0"], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--slices" in bad.stderr, bad.stderr


def test_license_is_mit():
    from pathlib import Path

    text = (Path(__file__).resolve().parent.parent / "LICENSE").read_text()
    assert text.startswith("MIT License\n\nCopyright (c) the torch_ao developers\n")
