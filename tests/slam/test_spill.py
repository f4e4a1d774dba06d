"""What the map reads again only at the end lives on disk with a run directory (pvslam_core.slam.spill): memory held
per retired edge and per frame stays small, and what is read back is bit-identical."""
import torch

from pvslam_core.geometry.lie import se3_exp, se3_mul
from pvslam_core.geometry.projective import reproject
from pvslam_core.geometry.testing import make_problem
from pvslam_core.slam.frame_poses import FramePoses
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.slam.spill import SpillStore
from pvslam_core.types import EdgeObservations

H, W = 30, 40  # the BA resolution of a 320x240 run


def tensor_bytes(obj, seen=None) -> int:
    """Bytes of the tensor storages reachable from ``obj`` through containers and object attributes."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        return obj.untyped_storage().nbytes()
    if isinstance(obj, dict):
        return sum(tensor_bytes(k, seen) + tensor_bytes(v, seen) for k, v in obj.items())
    if isinstance(obj, (list, tuple, set)):
        return sum(tensor_bytes(v, seen) for v in obj)
    if hasattr(obj, "__dict__") and not isinstance(obj, type):
        return tensor_bytes(vars(obj), seen)
    return 0


def test_the_store_reads_back_every_bit_on_disk_and_keeps_the_objects_in_memory(tmp_path):
    gen = torch.Generator().manual_seed(0)
    ts = (torch.randn(2, H, W, generator=gen), torch.randn(2, H, W, generator=gen).half(),
          torch.randint(0, 255, (3, 5), generator=gen, dtype=torch.uint8), torch.zeros(0, 2), torch.tensor(1.5))
    disk, mem = SpillStore(tmp_path), SpillStore()
    assert disk.on_disk and not mem.on_disk
    assert list(tmp_path.iterdir()) == []  # the file is unlinked: nothing is left behind
    hd, hm = disk.put(*ts), mem.put(*ts)
    back = disk.get(hd)
    for a, b in zip(ts, back):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a.view(-1).view(torch.uint8)
                                                                         if a.numel() else a, b.view(-1).view(
                                                                             torch.uint8) if b.numel() else b)
    assert all(a is b for a, b in zip(ts, mem.get(hm)))
    disk.drop(hd)
    assert len(disk) == 0
    disk.close()


def _graph(spill):
    g = FrameGraph(H, W, torch.tensor([40.0, 40.0, 20.0, 15.0]), spill=spill)
    for k in range(40):
        g.add_keyframe(k, float(k), torch.tensor([k, 0, 0, 0, 0, 0, 1.0]), torch.full((H, W), 1.0 + k))
    return g


def test_retired_edges_hold_no_observation_in_memory_with_a_spill_dir(tmp_path):
    gen = torch.Generator().manual_seed(1)
    graphs = [_graph(SpillStore(tmp_path)), _graph(None)]
    ii = torch.arange(0, 39).repeat(3)
    jj = torch.cat([torch.arange(1, 40), torch.arange(0, 39).roll(1), (torch.arange(0, 39) + 1).clamp(max=38)])
    keep = ii != jj
    ii, jj = ii[keep], jj[keep]
    obs = EdgeObservations(ii, jj, torch.rand(len(ii), 2, H, W, generator=gen) * W,
                           torch.rand(len(ii), 2, H, W, generator=gen))
    for g in graphs:
        g.add_edges(ii, jj)
        g.record_observations(obs)
        g.retire_edges(torch.ones(g.num_edges, dtype=torch.bool))
        g.remove_keyframe(5)
    disk, mem = graphs
    assert disk.num_retired == mem.num_retired > 60
    # in memory a retired edge holds its float16 offset and weight (2 x [2, h, w]); on disk only a handle
    assert tensor_bytes((mem._retired, mem.spill)) >= mem.num_retired * 4 * H * W * 2
    assert tensor_bytes((disk._retired, disk.spill)) < 64 * disk.num_retired
    a, b = (g.retired_observations(*g.retired_edges()) for g in graphs)
    assert torch.equal(a.target, b.target) and torch.equal(a.weight, b.weight)


def test_frame_correspondences_live_on_disk_and_refine_to_the_same_bits(tmp_path):
    pr = make_problem(n=3, seed=5, radius=2)
    coords, valid = reproject(pr.poses, pr.disps.double(), pr.intr.double(), torch.tensor([0]), torch.tensor([2]))
    target = coords[0].permute(2, 0, 1).float()
    weight = valid[0].float().expand(2, -1, -1).clone()
    ident = torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)
    results = []
    for spill in (SpillStore(tmp_path), None):
        g = pr.graph()
        fp = FramePoses(g, robust="cauchy", robust_scale=1.0, spill=spill)
        fp.add_keyframe(0, 0.0, g.id_of(0))
        entries = [fp.add_frame(7 + i, 0.7 + 0.01 * i, g.id_of(0), ident, target + 0.01 * i, weight)
                   for i in range(20)]
        held = tensor_bytes((entries, fp.spill))
        if spill is not None:  # a pose and a handle each
            assert held < 20 * 256
        else:  # target [2, h, w] in float32 each (the weight here is one shared tensor)
            assert held > 20 * target.numel() * 4
        inits = torch.stack([se3_mul(pr.poses[2], se3_exp(torch.tensor([0.01 * i, -0.02, 0.02, 0.01, -0.01, 0.0],
                                                                       dtype=torch.float64))) for i in range(20)])
        fp.refine_many_later(entries[:10], inits[:10])
        assert fp.refill(iters=4) == 20
        results.append(fp.poses()[1])
        fp.close()
    assert torch.equal(results[0], results[1])


class _Frontend:
    """Observations of any edge: a pattern of its ends (no priors)."""

    def observe(self, graph, ii, jj):
        n = len(ii)
        base = (ii * 7 + jj).float().reshape(n, 1, 1, 1)
        target = base + torch.linspace(0, 1, 2 * H * W).reshape(1, 2, H, W)
        return EdgeObservations(ii, jj, target, torch.sigmoid(target), dynamic=torch.full((n, H, W), 0.5))

    def depth_prior(self, graph, idx):
        return None

    def distance_prior(self, graph, idx):
        return None


def test_the_final_observations_of_active_and_retired_edges_are_the_joined_ones(tmp_path):
    from pvslam_core.slam.observe import EdgeObserver, concat

    g = _graph(SpillStore(tmp_path))
    fe = _Frontend()
    ob = EdgeObserver(g, fe)
    ii, jj = torch.arange(0, 20), torch.arange(1, 21)
    g.add_edges(ii, jj)
    ob.observe_edges(ii, jj)
    g.retire_edges(ii % 3 != 0)
    aii, ajj = g.all_edges()
    perm = torch.randperm(len(aii), generator=torch.Generator().manual_seed(2))
    aii, ajj = aii[perm], ajj[perm]
    got = ob.observe_any(aii, ajj)
    retired = g.is_retired(aii, ajj) & ~g.has_edges(aii, ajj)
    live, dead = torch.nonzero(~retired).squeeze(1), torch.nonzero(retired).squeeze(1)
    assert len(live) and len(dead)
    ref = concat([fe.observe(g, aii[live], ajj[live]), g.retired_observations(aii[dead], ajj[dead])],
                 torch.argsort(torch.cat([live, dead])))
    for name in ("ii", "jj", "target", "weight", "dynamic"):
        a, b = getattr(got, name), getattr(ref, name)
        assert a.dtype == b.dtype and torch.equal(a, b), name
