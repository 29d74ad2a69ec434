import numpy as np

from clrefract.adam import Adam, ParamGroup


def test_adam_minimises_a_quadratic_with_group_rates():
    target = np.linspace(-1, 1, 10)
    p = np.zeros(10)
    opt = Adam(10, [ParamGroup("a", 0, 5, 0.05), ParamGroup("b", 5, 10, 0.05)])
    for _ in range(500):
        opt.step(p, 2 * (p - target))
    assert np.abs(p - target).max() < 1e-2


def test_sparse_group_skips_zero_gradients_and_keeps_their_moments():
    p = np.ones(4)
    opt = Adam(4, [ParamGroup("table", 0, 4, 0.1, sparse=True)])
    opt.step(p, np.array([1.0, 0.0, -1.0, 0.0]))
    assert list(opt.t) == [1, 0, 1, 0]
    assert p[1] == 1.0 and p[3] == 1.0
    # first Adam step moves by lr in the sign of the gradient
    assert np.allclose(p[[0, 2]], [0.9, 1.1])
