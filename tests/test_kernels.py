"""The project's matrix kernels (``learners/kernels``): every output element one fixed FMA chain.

What must hold: the scalar (``std::fmaf``), AVX2 and AVX-512 paths give the same bits for the
forward product and both gradients at every shape the networks use, tails and strides included;
a population member's product does not depend on the other members; the results lie within the
error bound of a float32 sum of K products of the float64 reference; the bias gradient adds the
rows in order; and where no compiler works, ``numerics=fma`` falls back to ``portable`` with a
warning and says so in what it records.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from learners import kernels

ROOT = Path(__file__).resolve().parent.parent

if kernels.unavailable_reason():
    pytest.skip(f"the kernels cannot be built here: {kernels.unavailable_reason()}", allow_module_level=True)

from learners.kernels import ops  # noqa: E402

PATHS = kernels.isas()  # scalar always; avx2, avx512 where the CPU has them
# (R, M rows, K, N): the layers' shapes (rows 200, 256, 1,400 pairs; widths 1, 2, 6, 8, 100, 256),
# K of 1 and 2, K beyond a cache block (384) and beyond 4,096, and tails of every vector width.
SHAPES = [(1, 1, 1, 1), (1, 13, 1, 37), (3, 17, 2, 19), (2, 200, 8, 100), (2, 200, 100, 100), (2, 200, 100, 1),
          (2, 200, 100, 2), (3, 1400, 100, 1), (2, 256, 6, 100), (1, 64, 256, 256), (2, 33, 7000, 2),
          (2, 7, 5000, 100), (1, 100, 4100, 33), (2, 15, 385, 31), (2, 29, 9, 7), (2, 100, 200, 100)]


def operands(r: int, m: int, k: int, n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(r, m, k, generator=g), torch.randn(r, n, k, generator=g), torch.randn(r, n, generator=g),
            torch.randn(r, m, n, generator=g))


def layer(x, w, b, dy, isa):
    """Forward, input gradient, weight gradient and bias gradient of a stacked linear layer."""
    return (ops.bmm(x, w.transpose(1, 2), b, isa=isa), ops.bmm(dy, w, isa=isa),
            ops.bmm(dy.transpose(1, 2), x, isa=isa), ops.colsum(dy))


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)))
def test_every_path_gives_the_same_bits(shape):
    if len(PATHS) < 2:
        pytest.skip(f"this CPU runs only the {PATHS} path")
    x, w, b, dy = operands(*shape)
    results = {isa: layer(x, w, b, dy, isa) for isa in PATHS}
    for isa in PATHS[1:]:
        for name, ours, theirs in zip(("forward", "input grad", "weight grad"), results[isa], results["scalar"]):
            assert torch.equal(ours, theirs), f"{shape} {name}: the {isa} path differs from the scalar path"


def test_the_avx512_path_is_tested_where_the_cpu_has_it():
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    if " avx512f " in flags and " avx512vl " in flags:
        assert "avx512" in PATHS
    if " avx2 " in flags and " fma " in flags:
        assert "avx2" in PATHS


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)))
def test_within_the_error_bound_of_a_float32_sum(shape):
    """|fl(sum) - sum| <= gamma_K sum |a_ik b_kj| (gamma_K = K u / (1 - K u), u = 2^-24), and the
    bias's one rounded addition on top; against the float64 product."""
    x, w, b, dy = operands(*shape)
    u = 2.0 ** -24
    for a, bm, bias in ((x, w.transpose(1, 2), b), (dy, w, None), (dy.transpose(1, 2), x, None)):
        k = a.shape[2]  # the length of this product's sums
        gamma = k * u / (1 - k * u)
        ours = ops.bmm(a, bm, bias).double()
        exact = a.double() @ bm.double()
        magnitude = a.double().abs() @ bm.double().abs()
        bound = gamma * magnitude
        if bias is not None:
            exact = exact + bias.double().unsqueeze(1)
            bound = bound * (1 + u) + u * exact.abs() + 1e-300
        assert bool(((ours - exact).abs() <= bound).all()), f"{shape}: an element outside the bound"


@pytest.mark.parametrize("shape", [(5, 200, 100, 100), (4, 1400, 100, 1), (3, 256, 8, 100), (6, 33, 7000, 2)],
                         ids=lambda s: "x".join(map(str, s)))
def test_a_member_computes_what_it_computes_alone(shape):
    x, w, b, dy = operands(*shape)
    together = layer(x, w, b, dy, None)
    for member in (0, shape[0] - 1):
        alone = layer(x[member:member + 1], w[member:member + 1], b[member:member + 1], dy[member:member + 1], None)
        for ours, solo in zip(together, alone):
            assert torch.equal(ours[member], solo[0])


def test_strided_and_transposed_operands_give_the_same_bits_as_contiguous_copies():
    x, w, b, dy = operands(3, 120, 40, 50)
    xt = x.transpose(1, 2).contiguous().transpose(1, 2)  # column-major storage of the same values
    for isa in PATHS:
        assert torch.equal(ops.bmm(xt, w.transpose(1, 2), b, isa=isa),
                           ops.bmm(x, w.transpose(1, 2).contiguous(), b, isa=isa))
        assert torch.equal(ops.bmm(x[:, ::2], w.transpose(1, 2), isa=isa),
                           ops.bmm(x[:, ::2].contiguous(), w.transpose(1, 2), isa=isa))


def test_the_bias_gradient_adds_the_rows_in_order():
    _, _, _, dy = operands(2, 300, 1, 37)
    rows = dy.numpy()
    expected = np.zeros((2, 37), dtype=np.float32)
    for i in range(rows.shape[1]):
        expected = expected + rows[:, i]  # float32, one rounded addition per row
    assert np.array_equal(ops.colsum(dy).numpy(), expected)
    assert np.array_equal(ops.colsum(dy.transpose(1, 2).contiguous().transpose(1, 2)).numpy(), expected)


def test_the_stacked_layer_uses_them_and_its_gradients_are_theirs():
    from learners.networks import StackedLinear

    layer_ = StackedLinear(3, 8, 5)
    torch.nn.init.normal_(layer_.weight)
    torch.nn.init.normal_(layer_.bias)
    x = torch.randn(3, 4, 10, 8, requires_grad=True)
    previous = kernels.active()
    try:
        kernels.use(True)
        out = layer_(x)
        grad = torch.randn_like(out)
        out.backward(grad)
    finally:
        kernels.use(previous)
    flat, g = x.detach().reshape(3, 40, 8), grad.reshape(3, 40, 5)
    w = layer_.weight.detach()
    assert torch.equal(out.detach().reshape(3, 40, 5), ops.bmm(flat, w.transpose(1, 2), layer_.bias.detach()))
    assert torch.equal(x.grad.reshape(3, 40, 8), ops.bmm(g, w))
    assert torch.equal(layer_.weight.grad, ops.bmm(g.transpose(1, 2), flat))
    assert torch.equal(layer_.bias.grad, ops.colsum(g))


def test_bad_operands_are_refused_clearly():
    with pytest.raises(TypeError, match="float32 CPU tensor"):
        ops.bmm(torch.ones(1, 2, 3, dtype=torch.float64), torch.ones(1, 3, 2))
    with pytest.raises(ValueError, match="cannot multiply"):
        ops.bmm(torch.ones(1, 2, 3), torch.ones(1, 4, 2))
    with pytest.raises(ValueError, match="isa must be one of"):
        ops.bmm(torch.ones(1, 2, 3), torch.ones(1, 3, 2), isa="sse9")


def test_the_fma_peak_is_measured():
    vector = [isa for isa in PATHS if isa != "scalar"]
    if not vector:
        pytest.skip("no vector path on this CPU")
    assert kernels.peak_gflops(vector[-1], seconds=0.02) > 1.0


def test_without_a_compiler_fma_falls_back_to_portable_and_says_so(tmp_path):
    """... and Adam's correctly rounded square root to its float64 round trip (the same bits)."""
    code = ("import json, warnings\nwarnings.simplefilter('always')\nfrom engine import numerics\n"
            "with warnings.catch_warnings(record=True) as caught:\n    numerics.apply('fma')\n"
            "import numpy as np, torch\nfrom learners.optim import exact_sqrt\n"
            "x = torch.rand(1003) * 10\nsame = bool(np.array_equal(exact_sqrt([x])[0].numpy(), np.sqrt(x.numpy())))\n"
            "print(json.dumps({'effect': numerics.in_effect(), 'warnings': [str(w.message) for w in caught], "
            "'sqrt': same}))")
    env = {**os.environ, "CXX": "", "PATH": str(tmp_path), "RACING_KERNEL_CACHE": str(tmp_path / "cache")}
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout.splitlines()[-1])
    assert report["effect"]["mode"] == "portable" and report["effect"]["products"] == "torch"
    assert "no C++ compiler found" in report["effect"]["fallback"]
    assert any("running numerics=portable instead" in w for w in report["warnings"])
    assert report["sqrt"]  # Adam's square root falls back to the float64 round trip: still correctly rounded
