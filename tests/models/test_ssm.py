"""selective_scan against its plain-loop definition (random, hard and gradcheck cases), and
ConvSSM's forecast: finite, bounded and differentiable for any decay and history length."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
import torch.nn.functional as F
from device_params import DEVICES

from pcdet_atlas.models.ssm import ConvSSM, selective_scan, selective_scan_reference

# Error bound for float32 against the float64 reference, relative to ``_scale`` (the same scan on
# absolute values, which bounds |out| and every term summed into it): each output element goes
# through at most T + l / T + n + a few float32 roundings (local scan, chunk carries, sum over n,
# D, z) of 6e-8 each, ~2e-5 at l = 16384, T = 64, n = 4; rounding exp(delta A) compounds only
# as |cumsum(delta A)| exp(cumsum(delta A)) eps <= eps / e. 1e-4 leaves a 5x margin.
RTOL = {torch.float32: 1e-4, torch.float64: 1e-10}
# float32 subnormals (< 1.2e-38) lose relative precision; errors below this are not compared
TINY = {torch.float32: torch.finfo(torch.float32).tiny, torch.float64: 0.0}
NAMES = ("u", "delta", "A", "B", "C", "D", "z", "delta_bias")


def _log_uniform(lo: float, hi: float, shape: tuple, gen: torch.Generator) -> torch.Tensor:
    r = torch.rand(shape, generator=gen, dtype=torch.float64)
    return torch.exp(math.log(lo) + r * (math.log(hi) - math.log(lo)))


def _inputs(
    b: int, d: int, n: int, l: int, seed: int = 0, extreme: bool = False, scale: float = 1.0
) -> dict[str, torch.Tensor]:
    """float64 scan inputs. ``extreme``: delta log-uniform in [1e-6, 1e3] and |A| in
    [1e-4, 1e4]; ``scale`` multiplies u, B and C."""
    gen = torch.Generator().manual_seed(seed)

    def randn(*shape):
        return torch.randn(shape, generator=gen, dtype=torch.float64)

    if extreme:
        delta, A = _log_uniform(1e-6, 1e3, (b, d, l), gen), -_log_uniform(1e-4, 1e4, (d, n), gen)
    else:
        delta = 0.5 * torch.rand(b, d, l, generator=gen, dtype=torch.float64)
        A = -0.1 - torch.rand(d, n, generator=gen, dtype=torch.float64)
    return {
        "u": scale * randn(b, d, l),
        "delta": delta,  # (b, d, l)
        "A": A,  # (d, n)
        "B": scale * randn(b, n, l),
        "C": scale * randn(b, n, l),
        "D": randn(d),
        "z": randn(b, d, l),
        "delta_bias": 0.5 * torch.rand(d, generator=gen, dtype=torch.float64),
    }


def _cast(x: dict, dtype: torch.dtype, keep=NAMES, grad: bool = False) -> dict:
    """``x`` in ``dtype``, only the entries named in ``keep``; leaves requiring grad if asked."""
    return {k: v.to(dtype).requires_grad_(grad) for k, v in x.items() if k in keep}


def _reference_and_scale(x: dict, delta_softplus: bool = False):
    """The float64 reference on exactly ``x``'s values, and ``_scale`` (see RTOL)."""
    x = {k: v.detach().double() for k, v in x.items()}
    ref = selective_scan_reference(**x, delta_softplus=delta_softplus)
    absx = {**x, "u": x["u"].abs(), "B": x["B"].abs(), "C": x["C"].abs(), "z": None}
    if "D" in x:
        absx["D"] = x["D"].abs()
    scale = selective_scan_reference(**absx, delta_softplus=delta_softplus)
    if "z" in x:
        scale = scale * F.silu(x["z"]).abs()
    return ref, scale


def _assert_scan_close(out: torch.Tensor, ref: torch.Tensor, scale: torch.Tensor, dtype) -> None:
    err = (out.detach().double() - ref).abs()
    bound = RTOL[dtype] * (scale + TINY[dtype])
    assert torch.isfinite(out).all()
    assert (err <= bound).all(), f"max error / bound {(err / bound).max().item():.3g}"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("l", [1, 7, 64, 65, 200])
@pytest.mark.parametrize(
    "with_D,with_z,with_bias,softplus", list(itertools.product([False, True], repeat=4))
)
def test_matches_reference(dtype, l, with_D, with_z, with_bias, softplus):
    keep = ["u", "delta", "A", "B", "C"]
    keep += ["D"] * with_D + ["z"] * with_z + ["delta_bias"] * with_bias
    x = _cast(_inputs(2, 3, 4, l, seed=l), dtype, keep)
    out = selective_scan(**x, delta_softplus=softplus)
    _assert_scan_close(out, *_reference_and_scale(x, softplus), dtype)


@pytest.mark.parametrize("chunk_size", [1, 8, 64, 1000])
def test_chunk_size_independent(chunk_size):
    x = _cast(_inputs(2, 3, 4, 200, seed=1), torch.float32)
    out = selective_scan(**x, delta_softplus=True, chunk_size=chunk_size)
    ref, scale = _reference_and_scale(x, True)
    _assert_scan_close(out, ref, scale, torch.float32)
    out_64 = selective_scan(**x, delta_softplus=True, chunk_size=64)
    _assert_scan_close(out, out_64.double(), 2 * scale, torch.float32)  # both within 1x of ref


@pytest.mark.parametrize(
    "extreme,scale", [(True, 1.0), (False, 1e4), (True, 1e4)], ids=["delta_A", "1e4", "both"]
)
def test_hard_cases_long_sequence(extreme, scale):
    """l = 16384 with delta in [1e-6, 1e3], |A| in [1e-4, 1e4] and/or u, B, C of size 1e4."""
    x = _cast(_inputs(1, 2, 4, 16384, seed=2, extreme=extreme, scale=scale), torch.float32)
    x = {k: v.requires_grad_(True) for k, v in x.items()}
    out = selective_scan(**x)
    _assert_scan_close(out, *_reference_and_scale(x), torch.float32)
    out.sum().backward()
    for name in ("u", "delta", "A", "B", "C"):
        assert torch.isfinite(x[name].grad).all(), name


def test_zero_input_gives_exact_zero():
    x = _cast(_inputs(1, 2, 4, 16384, seed=3, extreme=True, scale=1e4), torch.float32)
    x["u"] = torch.zeros_like(x["u"])
    x = {k: v.requires_grad_(True) for k, v in x.items()}
    out = selective_scan(**x, delta_softplus=True)
    assert torch.equal(out, torch.zeros_like(out))
    out.sum().backward()
    assert all(torch.isfinite(v.grad).all() for v in x.values())
    for name in ("delta", "A", "B", "C", "D"):  # all act through u (or through h = 0)
        assert torch.equal(x[name].grad, torch.zeros_like(x[name])), name


def test_gradcheck():
    x = _cast(_inputs(1, 2, 3, 5, seed=4), torch.float64, grad=True)

    def fn(*args):  # chunk_size 2: padding and a carry across chunks
        return selective_scan(**dict(zip(NAMES, args)), delta_softplus=True, chunk_size=2)

    assert torch.autograd.gradcheck(fn, tuple(x[k] for k in NAMES))


def test_gradients_match_reference():
    x = _cast(_inputs(2, 3, 4, 37, seed=5), torch.float64, grad=True)
    g = torch.randn(2, 3, 37, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grads = torch.autograd.grad((selective_scan(**x, chunk_size=8) * g).sum(), list(x.values()))
    grads_ref = torch.autograd.grad((selective_scan_reference(**x) * g).sum(), list(x.values()))
    for name, got, want in zip(x, grads, grads_ref):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12, msg=name)


def test_inputs_unchanged_single_tensor():
    x = _cast(_inputs(2, 3, 4, 70, seed=6), torch.float32, grad=True)
    before = {k: v.detach().clone() for k, v in x.items()}
    out = selective_scan(**x, delta_softplus=True, chunk_size=16)
    out.sum().backward()
    assert isinstance(out, torch.Tensor)
    for k, v in x.items():
        assert torch.equal(v.detach(), before[k]), k


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_output_dtype(dtype):
    x = _cast(_inputs(1, 2, 3, 9, seed=7), dtype)
    assert selective_scan(**x).dtype == dtype


@pytest.mark.parametrize("device", DEVICES)
def test_device(device):
    x = {k: v.to(device) for k, v in _cast(_inputs(2, 3, 4, 100, seed=8), torch.float32).items()}
    out = selective_scan(**x, delta_softplus=True, chunk_size=16)
    assert out.device.type == device
    x_cpu = {k: v.cpu() for k, v in x.items()}  # the float64 reference runs on the CPU
    _assert_scan_close(out.cpu(), *_reference_and_scale(x_cpu, True), torch.float32)


@pytest.mark.parametrize("name", NAMES)
def test_bad_shape_raises(name):
    x = _cast(_inputs(2, 3, 4, 10), torch.float32)
    # u and A define b, d, l and n: break their rank / d; every other argument loses a step
    x[name] = {"u": x["u"][0], "A": x["A"][:-1]}.get(name, x[name][..., :-1])
    with pytest.raises(ValueError, match=f"selective_scan: {name} must be"):
        selective_scan(**x)


def test_empty_sequence_and_bad_chunk_raise():
    x = _cast(_inputs(2, 3, 4, 10), torch.float32)
    with pytest.raises(ValueError, match="chunk_size"):
        selective_scan(**x, chunk_size=0)
    x0 = {k: v[..., :0] if v.dim() == 3 else v for k, v in x.items()}
    with pytest.raises(ValueError, match="l must be >= 1"):
        selective_scan(**x0)


# ConvSSM ------------------------------------------------------------------------------------


def _model(a_log: float | None = None, seed: int = 0) -> ConvSSM:
    torch.manual_seed(seed)
    model = ConvSSM(in_channels=3, state_channels=4)
    if a_log is not None:
        with torch.no_grad():
            model.A_log.fill_(a_log)
    return model


def _history(kind: str, k: int, seed: int = 0) -> torch.Tensor:
    """(2, k, 3, 8, 8) history maps: zero, constant, or random of size 1e4."""
    if kind == "zero":
        return torch.zeros(2, k, 3, 8, 8)
    if kind == "constant":
        return torch.full((2, k, 3, 8, 8), 3.0)
    return 1e4 * torch.randn(2, k, 3, 8, 8, generator=torch.Generator().manual_seed(seed))


def _output_bound(model: ConvSSM, x: torch.Tensor) -> torch.Tensor:
    """(3,) bound on |forecast| per channel: each state is a convex combination (weights summing
    to 1 - A_bar^k <= 1) of past B(X_j), so |h| <= M = max |B(X_j)|; zero padding only drops
    terms, so |C(h)[o]| <= ||W_C[o]||_1 M + |b_C[o]|; plus |D[o]| max |X_k[o]|."""
    with torch.no_grad():
        m = model.B(x.flatten(0, 1)).abs().max()
        w1 = model.C.weight.abs().sum((1, 2, 3))  # (3,)
        skip = model.D.abs() * x[:, -1].abs().amax((0, 2, 3))  # (3,)
        return w1 * m + model.C.bias.abs() + skip


@pytest.mark.parametrize("a_log", [-30.0, 0.0, 30.0, 100.0])
@pytest.mark.parametrize("k", [1, 256])
@pytest.mark.parametrize("kind", ["zero", "constant", "large"])
def test_convssm_finite_bounded_differentiable(a_log, k, kind):
    model = _model(a_log)
    x = _history(kind, k)
    out = model(x)
    assert out.shape == (2, 3, 8, 8)
    assert torch.isfinite(out).all()
    bound = _output_bound(model, x)[None, :, None, None]
    assert (out.detach().abs() <= bound * (1 + 1e-5)).all()
    out.sum().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("a_log", [0.0, 30.0])
def test_convssm_constant_input_converges_without_growth(a_log):
    """Constant history: h_k = (1 - A_bar^k) B(X) rises to the steady state B(X), never past it."""
    model = _model(a_log)
    x = _history("constant", 256)
    with torch.no_grad():
        bound = _output_bound(model, x)[None, :, None, None]
        for k in (1, 2, 4, 16, 64, 256):
            assert (model(x[:, -k:]).abs() <= bound * (1 + 1e-5)).all(), k
        steady = model.C(model.B(x[:, -1])) + model.D[:, None, None] * x[:, -1]
        torch.testing.assert_close(model(x), steady)  # A_bar^256 <= e^-256: converged


@pytest.mark.parametrize("a_log", [-80.0, -30.0, 0.0, 30.0, 100.0, 1e4])
def test_convssm_decay_in_unit_interval(a_log):
    a_bar, gain = _model(a_log).decay()
    assert ((a_bar >= 0) & (a_bar <= 1)).all()
    assert ((gain > 0) & (gain <= 1)).all()  # expm1: not rounded to 0 for tiny rates
    torch.testing.assert_close(a_bar + gain, torch.ones_like(a_bar))


def test_convssm_default_decays_span_memories():
    a_bar, _ = _model().decay()
    assert a_bar.min() < 0.2 and a_bar.max() > 0.9


def test_convssm_forecast_depends_on_input():
    model = _model()
    with torch.no_grad():
        model.D.zero_()  # through the state alone
        out_a, out_b = model(_history("large", 1, seed=1)), model(_history("large", 1, seed=2))
    assert not torch.allclose(out_a, out_b)


@pytest.mark.parametrize("shape", [(2, 3, 8, 8), (2, 1, 4, 8, 8), (2, 0, 3, 8, 8)])
def test_convssm_bad_shape_raises(shape):
    with pytest.raises(ValueError, match=r"ConvSSM: x must be \(b, k >= 1, 3, h, w\)"):
        _model()(torch.zeros(shape))
