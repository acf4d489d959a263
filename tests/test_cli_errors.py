"""Bad input on the command line: one clear line naming the argument, exit status 2, no traceback,
and no output file written."""
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
