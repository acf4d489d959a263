"""The walk's ``"edge_aware"`` fetch: bilinear inside a surface, the nearest texel across a depth edge."""
import math

import pytest
import torch

from torch_ao import BitmaskAO
from torch_ao.camera import PinholeCamera
from torch_ao.examples import floor_wall_gbuffer, plane_gbuffer, planes_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels.bitmask import kernel_covers
from torch_ao.screen_truth import _continuous_cells, _fetch
from torch_ao.walk import Footprint, Frame, SlicePattern, march
from torch_ao.walk.fetch import EDGE_MIN_RATIO, continuous_cell_image, continuous_cells
from torch_ao.walk.sample import fetch_sample

NEAR, FAR = 2.0, 4.0


def step_gbuffer(H=24, W=32, dtype=torch.float64, edge_column=16, position=False):
    """Depth ``NEAR`` left of column ``edge_column``, ``FAR`` from it on (facing the camera)."""
    depth = torch.full((1, 1, H, W), FAR, dtype=dtype)
    depth[..., :edge_column] = NEAR
    cam = PinholeCamera.from_fov(60.0, H, W).to(dtype=dtype)
    normals = torch.zeros(1, 3, H, W, dtype=dtype)
    normals[:, 2] = 1
    gb = GBuffer(depth, cam, normals=normals)
    return GBuffer(depth, cam, normals=normals, position=gb.positions()) if position else gb


def _read(frame, su, sv, fetch):
    foot, inside = Footprint.at(frame, torch.zeros_like(su, dtype=torch.long), su, sv, fetch)
    return foot, foot.position(frame)


@pytest.mark.parametrize("position", [False, True])
def test_step_edge_reads_the_nearer_texel_not_a_blend(position):
    frame = Frame(step_gbuffer(position=position))
    su = torch.tensor([15.3, 15.7, 3.4, 25.6], dtype=torch.float64)  # between columns 15 (near) and 16 (far); inside
    sv = torch.tensor([2.2, 12.6, 1.5, 3.1], dtype=torch.float64)
    _, p = _read(frame, su, sv, "edge_aware")
    assert torch.equal(-p[:, 2], torch.tensor([NEAR, FAR, NEAR, FAR], dtype=torch.float64))
    # at the sample's own screen position: the texel's depth unprojected there (x = (u - cx) / fx * depth)
    cx, fx = frame.cx[0], frame.fx[0]
    assert torch.allclose(p[:, 0], (su - cx) / fx * -p[:, 2], rtol=1e-13)
    _, blend = _read(frame, su, sv, "bilinear")
    w = su[:2] - 15  # perspective-correct blend of 1/depth: neither texel's depth
    assert torch.allclose(-blend[:2, 2], 1 / ((1 - w) / NEAR + w / FAR), rtol=1e-13)


@pytest.mark.parametrize("position", [False, True])
def test_on_a_plane_edge_aware_is_bilinear_exactly(position):
    gb = plane_gbuffer(24, 32, tilt_degrees=70.0, dtype=torch.float64)  # up to grazing at the top
    if position:
        gb = GBuffer(gb.depth, gb.camera, normals=gb.normals, position=gb.positions())
    frame = Frame(gb)
    g = torch.Generator().manual_seed(1)
    su = torch.rand(500, generator=g, dtype=torch.float64) * 31
    sv = torch.rand(500, generator=g, dtype=torch.float64) * 23
    foot, p = _read(frame, su, sv, "edge_aware")
    ref_foot, ref = _read(frame, su, sv, "bilinear")
    on = frame.valid[ref_foot.index.long()].all(-1)  # footprints on the plane (not across its horizon)
    assert float(on.double().mean()) > 0.7
    assert torch.equal(foot.index[on], ref_foot.index[on])  # every cell of the plane is continuous
    assert torch.equal(p[on], ref[on])
    assert (foot.index[~on] == foot.index[~on][:, :1]).all()  # across the horizon: the nearest texel


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tilt", [85.0, 89.0])
@pytest.mark.parametrize("roll", [0.0, 30.0])
def test_grazing_planes_are_continuous_everywhere(tilt, roll, dtype):
    # a plane tilted `tilt` degrees from facing the camera at the image centre (nearer 90 towards its
    # horizon), its tilt axis rolled `roll` degrees so that both rows and columns step in depth
    t, r = math.radians(tilt), math.radians(roll)
    normal = (-math.sin(t) * math.sin(r), math.sin(t) * math.cos(r), math.cos(t))
    H, W = 36, 48
    gb = planes_gbuffer([(normal, -4.0 * math.cos(t), None)], PinholeCamera.from_fov(60.0, H, W), dtype=dtype)
    valid = gb.valid[0, 0]
    facing = torch.rad2deg(torch.acos((gb.view_normals() * -gb.positions()).sum(1)[0]
                                      / gb.positions().norm(dim=1)[0]))[valid]
    assert float(facing.min()) < tilt < float(facing.max()) and float(facing.max()) > 89.5
    inverse = torch.where(gb.valid, gb.safe_depth.reciprocal(), 0.0)[0, 0]
    # every cell of four valid texels is one surface; those touching the horizon are edges
    cells = continuous_cell_image(inverse)
    on = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
    assert int(on.sum()) > 100 and int((~on).sum()) > 0
    assert torch.equal(cells, on)
    # and the fetch reads it bilinearly there, exactly
    frame = Frame(gb)
    g = torch.Generator().manual_seed(4)
    su = torch.rand(2000, generator=g, dtype=dtype) * (W - 1)
    sv = torch.rand(2000, generator=g, dtype=dtype) * (H - 1)
    foot, p = _read(frame, su, sv, "edge_aware")
    ref_foot, ref = _read(frame, su, sv, "bilinear")
    inside = frame.valid[ref_foot.index.long()].all(-1)
    assert float(inside.double().mean()) > 0.3
    assert torch.equal(foot.index[inside], ref_foot.index[inside]) and torch.equal(p[inside], ref[inside])


def test_cell_rule_closed_form():
    inv = 1 / torch.tensor([[2.0, 2.0, 2.02, 2.04], [2.0, 2.0, 2.0, 2.1], [2.0, 2.0, 2.0, 4.0]], dtype=torch.float64)
    assert continuous_cells(inv, EDGE_MIN_RATIO).tolist() == [True, False, False]
    assert continuous_cells(inv, 1.2).tolist() == [True, True, False]
    assert not continuous_cells(torch.tensor([0.5, 0.5, 0.5, 0.0]), 1.1).item()  # an invalid texel: an edge

    def cells(inverse_rows):
        return continuous_cell_image(torch.tensor(inverse_rows, dtype=torch.float64)).tolist()

    # a plane: inverse depth affine in screen space, however steep (depth 1 ... 5 over five texels)
    plane = [[1.0 - 0.2 * x - 0.01 * y for x in range(5)] for y in range(3)]
    assert all(all(row) for row in cells(plane)) and len(cells(plane)) == 2 and len(cells(plane)[0]) == 4
    # creases: the jump across one lies between its sides' (a floor meeting a wall; a ridge)
    assert cells([[0.5, 0.6, 0.7, 0.75, 0.8, 0.85]] * 2) == [[True] * 5]
    assert cells([[0.5, 0.6, 0.7, 0.8, 0.7, 0.6]] * 2) == [[True] * 5]
    # a step (a slat at depth 2 before a wall at depth 2.3, ratio 1.15): only the cell across it is an edge
    step = [[0.5, 0.5, 0.5, 1 / 2.3, 1 / 2.3, 1 / 2.3]] * 2
    assert cells(step) == [[True, True, False, True, True]]
    # a one-texel pole before the floor: both cells beside it are edges; a step within 2 % is not
    assert cells([[0.25, 0.25, 0.5, 0.25, 0.25]] * 2) == [[True, False, False, True]]
    assert cells([[0.5, 0.5, 0.5 / 1.019, 0.5 / 1.019]] * 2) == [[True, True, True]]
    assert cells([[0.5, 0.5, 0.0, 0.5]] * 2) == [[True, False, False]]  # background
    # a pair alone in its row (a plane's corner at its horizon): one surface when the pair below it has its jump
    assert cells([[0.0, 0.05, 0.28, 0.0], [0.2, 0.3, 0.53, 0.76]]) == [[False, True, False]]
    assert cells([[0.0, 0.05, 0.28, 0.0], [0.2, 0.3, 0.35, 0.4]]) == [[False, False, False]]


def test_walk_and_screen_truth_read_the_same_surface():
    # random near/far blocks over a slanted surface: many edge cells and many smooth ones
    g = torch.Generator().manual_seed(2)
    H, W = 24, 32
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    depth = (3 + 0.05 * u + 0.03 * v) * torch.where(torch.rand(H, W, generator=g) < 0.3, 2.0, 1.0)
    depth[0, 0] = 0  # a background texel
    cam = PinholeCamera.from_fov(60.0, H, W)
    gb = GBuffer(depth[None, None], cam)
    frame = Frame(gb)
    su = torch.rand(4000, generator=g) * (W - 1)
    sv = torch.rand(4000, generator=g) * (H - 1)
    foot, _ = Footprint.at(frame, torch.zeros(4000, dtype=torch.long), su, sv, "edge_aware")
    walk_inverse = torch.where(frame.valid[foot.index.long()], frame.inverse_depth[foot.index.long()], -1.0)
    walk_depth = 1 / (walk_inverse[:, 0] * (1 - foot.fu) * (1 - foot.fv) + walk_inverse[:, 1] * foot.fu * (1 - foot.fv)
                      + walk_inverse[:, 2] * (1 - foot.fu) * foot.fv + walk_inverse[:, 3] * foot.fu * foot.fv)
    # the truth's surfaces: inverse depth, -_BIG on background, its cells and its grid_sample fetch
    inv = torch.where(gb.valid, gb.safe_depth.reciprocal(), torch.full_like(gb.depth, -1e30))
    cells = _continuous_cells(inv, None)
    grid = torch.stack((su / (W - 1) * 2 - 1, sv / (H - 1) * 2 - 1), -1)[:, None]
    sampled, nearest = _fetch((inv, cells, "edge_aware", None), grid, (H, W))
    truth_inverse = sampled[0, :, 0]
    single = (foot.index == foot.index[:, :1]).all(-1)
    assert torch.equal(single, nearest[:, 0]) and 0.2 < float(single.double().mean()) < 0.8
    ok = truth_inverse > 0  # both read the background as no surface
    assert torch.equal(ok, frame.valid[foot.index.long()].all(-1))
    assert torch.allclose(walk_depth[ok], 1 / truth_inverse[ok], rtol=1e-5)


def _positions_of(depth_values, cam, normals, su, sv):
    frame = Frame(GBuffer(depth_values, cam, normals=normals))
    foot, _ = Footprint.at(frame, torch.zeros_like(su, dtype=torch.long), su, sv, "edge_aware")
    return foot.position(frame)


def test_gradients_match_finite_differences_in_continuous_and_edge_cells():
    gb = step_gbuffer(5, 8, edge_column=4)  # the cell rule looks at neighbours, not at the resolution
    g = torch.Generator().manual_seed(3)
    depth = (gb.depth * (1 + 0.02 * torch.rand(gb.depth.shape, generator=g, dtype=torch.float64))).requires_grad_()
    su = torch.tensor([1.3, 5.6, 3.3, 3.8], dtype=torch.float64, requires_grad=True)  # smooth, smooth, edge, edge
    sv = torch.tensor([2.2, 1.7, 1.4, 2.9], dtype=torch.float64, requires_grad=True)
    frame = Frame(GBuffer(depth.detach(), gb.camera, normals=gb.normals))
    foot, _ = Footprint.at(frame, torch.zeros(4, dtype=torch.long), su.detach(), sv.detach(), "edge_aware")
    assert ((foot.index == foot.index[:, :1]).all(-1)).tolist() == [False, False, True, True]
    assert torch.autograd.gradcheck(lambda d, u, v: _positions_of(d, gb.camera, gb.normals, u, v), (depth, su, sv))


class Along:
    """Sums weighted along_view / along_tangent of every (batched) step."""

    batch_steps = True

    def __init__(self):
        self.loss = 0

    def begin_walk(self, q):
        pass

    def begin_slice(self, q, geom):
        return None

    def step(self, state, q, geom, sample):
        w = torch.linspace(-1, 1, sample.along_view.shape[0], dtype=torch.float64)
        self.loss = self.loss + (w * sample.along_view).sum() + (w.flip(0) * sample.along_tangent).sum()
        return state

    def end_slice(self, state, q, geom):
        return {"one": torch.ones_like(q.depth)[:, None]}

    def finish(self, sums, q, num_slices):
        return {"visibility": sums["one"] / num_slices}


@pytest.mark.parametrize("border", ["drop", "clamp"])
def test_fused_gradients_match_plain_autograd_across_edges(monkeypatch, border):
    import torch_ao.walk as walk
    from torch_ao.walk.protocol import SliceAccumulator

    grads = []
    for fused in (True, False):
        monkeypatch.setattr(walk.Footprint, "fusable", lambda self, frame: fused)
        gb = step_gbuffer(12, 16, edge_column=8)
        depth = (gb.depth * (1 + 0.02 * torch.rand(gb.depth.shape, generator=torch.Generator().manual_seed(4),
                                                   dtype=torch.float64))).requires_grad_()
        radius = torch.tensor(1.2, dtype=torch.float64, requires_grad=True)
        acc = type("A", (Along, SliceAccumulator), {})()
        march(Frame(GBuffer(depth, gb.camera, normals=gb.normals)),
              SlicePattern(3, 4, radius, fetch="edge_aware", border=border, step_power=1.5), acc)
        grads.append(torch.autograd.grad(acc.loss, (depth, radius)))
    assert grads[0][0].abs().max() > 0 and grads[0][1] != 0
    for a, b in zip(*grads):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


def test_the_own_texel_never_occludes_through_an_edge_cell():
    frame = Frame(step_gbuffer())
    q = frame.queries
    # query (u=15, v=2) on the near side of the edge; a sample 0.3 px toward the far side reads texel 15 again
    row = int(((q.u == 15) & (q.v == 2)).nonzero()[0])
    pick = q.map_rows(lambda x: x[row:row + 1])
    offset = torch.tensor([[0.3, 0.2]], dtype=torch.float64)
    own = fetch_sample(frame, pick, None, 1, 0, offset, fetch="edge_aware", border="drop")
    assert not own.valid.item()
    beyond = fetch_sample(frame, pick, None, 1, 0, offset + torch.tensor([[0.4, 0.0]], dtype=torch.float64),
                          fetch="edge_aware", border="drop")
    assert beyond.valid.item() and float(-beyond.position[0, 2]) == FAR


def test_methods_take_it_and_the_kernels_read_it():
    gb, _ = floor_wall_gbuffer(24, 32, pitch_degrees=-60.0)  # a crease, no depth edge
    for variant in ("default", "exact"):  # no depth edge: the same visibility as the bilinear fetch's tensor path
        with torch.no_grad():
            edge = BitmaskAO(preset="low", radius=1.0, variant=variant, fetch="edge_aware", backend="torch")(gb).visibility
            plain = BitmaskAO(preset="low", radius=1.0, variant=variant, fetch="bilinear", backend="torch")(gb).visibility
        assert torch.equal(edge, plain) and float(edge[gb.valid].mean()) < 0.99
    assert BitmaskAO(variant="exact").fetch == "edge_aware" and BitmaskAO().fetch == "bilinear"
    assert BitmaskAO(variant="exact", fetch="bilinear").fetch == "bilinear"
    # the sector kernel reads it (tests/test_kernels_hard_models.py), as the exact union's (tests/test_kernels_exact.py)
    assert kernel_covers(BitmaskAO(preset="low", radius=1.0, fetch="edge_aware"), gb) is None
    assert kernel_covers(BitmaskAO(preset="low", radius=1.0, fetch="bilinear"), gb) is None
    with pytest.raises(ValueError, match="fetch"):
        BitmaskAO(fetch="edgeaware")
