"""dynamic_persist: a keyframe keeps the mask it inherited from its reference OR-ed into the later judgements of its
edges (a vehicle seen moving once stays masked while tracked); off (the default), the edge's own judgement replaces
the inherited mask."""
import torch

from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend

import _flow_scenes as S
from test_dynamic import BA_H, BA_W, _graph3, _scene


def _run(persist: bool):
    imgs, g, _ = _scene()
    fe = FlowFrontend(FlowFrontendConfig(preset="medium", dynamic_persist=persist))
    fe.add_keyframe(0, S.frame(imgs[0], 0), None)
    fe.add_keyframe(1, S.frame(imgs[1], 1), None)
    fe.observe(g, torch.tensor([0, 1]), torch.tensor([1, 0]))
    fe.track(S.frame(imgs[2], 2), None)
    fe.add_keyframe(2, S.frame(imgs[2], 2), None)
    inherited = fe._kfs[2].dyn.clone()
    extra = torch.zeros(BA_H, BA_W, dtype=torch.bool)
    extra[1:4, 1:4] = True  # a region the reference saw moving that this pair's geometry does not flag
    fe._kfs[2].dyn = torch.maximum(inherited, extra.float())
    if persist:  # what add_keyframe keeps of the inherited mask
        fe._kfs[2].dyn_prior = fe._kfs[2].dyn > 0
    g3 = _graph3()
    first = fe.observe(g3, torch.tensor([2]), torch.tensor([1])).dynamic[0]
    judged = fe.observe(g3, torch.tensor([2]), torch.tensor([1])).dynamic[0]
    return first, judged, extra


def test_inherited_mask_persists_only_when_asked():
    assert not FlowFrontendConfig().dynamic_persist
    first, judged, extra = _run(persist=True)
    assert bool((first[extra] > 0).all())  # first observation: the inherited mask, both ways
    assert bool((judged[extra] > 0).all())  # judged by the edge's own residuals, the inherited region stays
    first0, judged0, _ = _run(persist=False)
    assert torch.equal(first0, first)
    assert not bool((judged0[extra] > 0).any())  # the default: the edge's own judgement replaces it
    # what the edge judged by itself is in both
    assert bool(((judged0 > 0) <= (judged > 0)).all())
