"""The simulator's motion (visvec.sim.simulate)."""

import numpy as np


def test_body_rates_of_a_turn_about_the_lab_vertical():
    from visvec.rotations import euler_to_matrix
    from visvec.sim.simulate import body_rates

    w = np.radians(15.0)
    R = np.array([euler_to_matrix(0.4 + w * k / 30.0, 0.05, -0.03) for k in range(5)])
    for k, om in enumerate(body_rates(R, 1.0 / 30.0)):
        np.testing.assert_allclose(om, R[k].T @ [0.0, 0.0, w], atol=1e-12)
