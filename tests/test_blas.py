"""The numpy-BLAS product of the generator's shared MLPs equals torch's, forward and backward."""

import torch

from icpbench.learning import blas


def test_linear_matches_addmm_and_its_gradients():
    gen = torch.Generator().manual_seed(0)
    w = torch.randn(5, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    x = torch.randn(4, 300, dtype=torch.float64, generator=gen, requires_grad=True)
    b = torch.randn(5, dtype=torch.float64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(blas.linear, (w, x, b))
    g = torch.randn(5, 300, dtype=torch.float64, generator=gen)
    got = torch.autograd.grad((blas.linear(w, x, b) * g).sum(), (w, x, b))
    want = torch.autograd.grad((torch.addmm(b[:, None], w, x) * g).sum(), (w, x, b))
    for a, e in zip(got, want, strict=True):
        torch.testing.assert_close(a, e, rtol=1e-12, atol=1e-12)


def test_linear_in_float32_agrees_with_addmm_within_rounding():
    gen = torch.Generator().manual_seed(1)
    w, x, b = (torch.randn(*s, generator=gen) for s in ((64, 32), (32, 5000), (64,)))
    torch.testing.assert_close(blas.linear(w, x, b), torch.addmm(b[:, None], w, x),
                               rtol=1e-5, atol=1e-5)
    assert blas.eligible(w, x, b)
    assert not blas.eligible(w, x.T, b)  # a transposed (non-contiguous) x is not
    assert not blas.eligible(w.double(), x, b)  # mixed dtypes are not
