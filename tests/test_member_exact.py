"""A member's numbers never depend on who else is in its population: tested hard at the one place that decides
it for element-wise functions (losses.functional.as_alone, per_member), at every size up to past both vector
loops' steps, and once end to end per family at the grids' size (13).

On 35048d1 an 8-member SAC population's member differed from its solo run at its first acting episode:
TorchRL's softplus of the actor's scale on ``[R, 1, 2]`` took ATen's scalar code alone (2 elements) and its
vector code from 8 members on (16 elements, one AVX2 loop step), which round differently."""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from losses.functional import as_alone, loop_bytes, per_member

SIZES = (1, 2, 5, 7, 8, 9, 13, 16, 17, 33)
SHAPES = ((2,), (1, 2), (1, 4), (3, 2), (50, 2), (256, 2), (7,))


@pytest.mark.parametrize("fn", [F.softplus, torch.tanh, torch.exp], ids=["softplus", "tanh", "exp"])
def test_each_member_gets_the_bits_of_its_tensor_alone_forward_and_backward(fn):
    g = torch.Generator().manual_seed(0)
    for shape in SHAPES:
        pool = torch.randn(max(SIZES), *shape, generator=g) * 4
        for members in SIZES:
            x = pool[:members].clone().requires_grad_()
            out = as_alone(fn, x)
            grad = torch.randn(out.shape, generator=g)
            out.backward(grad)
            for r in range(members):
                alone = pool[r:r + 1].clone().requires_grad_()
                expected = fn(alone)  # what a solo run computes: its own tensor, one member
                expected.backward(grad[r:r + 1])
                assert torch.equal(out[r:r + 1].detach(), expected.detach()), (shape, members, r)
                assert torch.equal(x.grad[r:r + 1], alone.grad), (shape, members, r)


def test_a_stacked_softplus_would_not_be_exact_without_it():
    """The failure as_alone removes, shown on this machine's kernels (where its vector and scalar softplus
    round alike, there is nothing to show and the test says so)."""
    g = torch.Generator().manual_seed(1)
    step = loop_bytes() // 4
    pool = torch.randn(step, 1, 2, generator=g) * 4
    plain = F.softplus(pool)  # one vector loop step: every element in vector code
    alone = torch.cat([F.softplus(pool[r:r + 1]) for r in range(step)])  # 2 elements each: scalar code
    if torch.equal(plain, alone):
        pytest.skip("this CPU's vector and scalar softplus round these values alike")
    assert torch.equal(as_alone(F.softplus, pool), alone)


def test_per_member_gives_every_member_the_vector_code_whatever_its_place():
    g = torch.Generator().manual_seed(2)
    pool = torch.randn(33, 3, 2, generator=g) * 4
    for members in SIZES:
        out = per_member(F.softplus, pool[:members])
        assert all(torch.equal(out[r], per_member(F.softplus, pool[r:r + 1])[0]) for r in range(members))


def test_the_actor_heads_and_the_losses_draw_use_it():
    """The SAC family's scale (MemberNormalParamExtractor), its acting sample and the losses' tanh-normal
    log-probability (DrawnTanhNormal) of a member equal those of the member alone, at a minibatch of 50 rows."""
    from learners.networks import MemberNormalParamExtractor
    from losses.td import DrawnTanhNormal

    g = torch.Generator().manual_seed(3)
    extractor = MemberNormalParamExtractor()
    heads = torch.randn(13, 1, 4, generator=g) * 3
    loc, scale = extractor(heads)
    for r in range(13):
        own_loc, own_scale = extractor(heads[r:r + 1])
        assert torch.equal(scale[r:r + 1], own_scale) and torch.equal(loc[r:r + 1], own_loc)
    loc, scale = torch.randn(13, 50, 2, generator=g), F.softplus(torch.randn(13, 50, 2, generator=g))
    noise = torch.randn(13, 50, 2, generator=g)
    sample, log_prob = DrawnTanhNormal(loc, scale, noise, low=-1.0, high=1.0).rsample_and_log_prob()
    for r in (0, 7, 12):
        own = DrawnTanhNormal(loc[r:r + 1], scale[r:r + 1], noise[r:r + 1], low=-1.0, high=1.0).rsample_and_log_prob()
        assert torch.equal(sample[r:r + 1], own[0]) and torch.equal(log_prob[r:r + 1], own[1])


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["sac", "td3", "spg_p_multi"])
def test_a_member_of_thirteen_is_its_solo_run(tmp_path, algo):
    """One learner of each kind of actor (tanh-normal, deterministic, the paper's Gaussian) at the grids'
    population size, a minibatch whose rows per member are not a multiple of a vector loop's step."""
    from tests.test_config import load
    from engine.runner import train_population

    seed = 2067791
    run = [f"algo={algo}", "er=memory", "episodes=7", "progress=false", "logger=none", "algo.minibatch_size=50"]
    train_population(load(*run, f"seed={seed}"), tmp_path / "solo")
    train_population(load(*run, f"seeds=[{seed},{','.join(map(str, range(1, 13)))}]"), tmp_path / "thirteen")
    assert ((tmp_path / "thirteen" / f"seed{seed}" / "metrics.csv").read_bytes()
            == (tmp_path / "solo" / "metrics.csv").read_bytes())
