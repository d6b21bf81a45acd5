"""The pixel fit of the triangle's edges (visvec.detect.photometric, `refine = "pixels"`):
more precise than the edge lines, an honest covariance, and refused where it disagrees
with them."""

from dataclasses import replace

import numpy as np

from visvec.data import Status
from visvec.detect import TriangleDetector
from visvec.detect import triangle as tri
from visvec.detect.edges import fit_edges, intersect
from visvec.detect.photometric import _intersections, _vertex_gain, refine
from visvec.geometry import project_target
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

from conftest import attitudes


def _pixels(rig):
    return replace(rig, detect=replace(rig.detect, refine="pixels"))


def test_pixel_fit_is_more_precise_than_the_lines_and_its_sigma_is_honest(rig320):
    """Ten attitudes, four noise draws each, 320x240: the vertices of the pixel fit err
    about 0.75x as much as the edge lines' (benchmarks/triangle_crb.py: at 1.0-1.25x
    the Cramér-Rao bound against the lines' 1.35-1.9x), and their error over their
    sigma has unit RMS."""
    dets = {k: TriangleDetector(r) for k, r in (("lines", rig320), ("pixels", _pixels(rig320)))}
    err = {k: [] for k in dets}
    z = []
    for k, R in enumerate(attitudes(10, 21)):
        truth = rig320.camera.undistort(project_target(rig320, R))
        for j in range(4):
            img = render_frame(rig320, R, Scene(), rng=700 + 10 * k + j)
            for name, det in dets.items():
                d = det.detect(img)
                assert d.status is Status.OK, d.reason
                e = (d.points_n - truth).ravel()
                err[name].append(e)
                if name == "pixels":
                    z.append(e / np.sqrt(np.diag(d.cov_n)))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}
    assert rms["pixels"] < 0.85 * rms["lines"], rms
    zr = float(np.sqrt(np.mean(np.square(z))))
    assert 0.8 < zr < 1.2, zr


def test_a_pixel_fit_that_disagrees_with_the_lines_is_not_taken(rig320):
    """The lines are robust, the pixel fit is not: vertices that the pixel fit moved by
    more than the lines' covariance allows are the lines' own, and those that agree are
    the pixel fit's."""
    R = attitudes(1, 5)[0]
    img = render_frame(rig320, R, Scene(), rng=3)
    # the edge fit from the true corners (a detector's coarse corners would do)
    fit = fit_edges(img, project_target(rig320, R), rig320.camera)
    xy, cov = intersect(fit)
    pf = refine(img, fit.normals, fit.offsets, fit.width, rig320.camera)
    assert pf.ok
    got, got_cov = tri._pixel_fit(img, fit, xy, cov, rig320.camera)
    np.testing.assert_array_equal(got, pf.xy)
    np.testing.assert_array_equal(got_cov, pf.cov)
    # lines 8 sigma away from what the pixels say: the pixel fit is refused
    far = xy + 8.0 * np.sqrt(np.diag(cov)).reshape(3, 2)
    got, got_cov = tri._pixel_fit(img, fit, far, cov, rig320.camera)
    np.testing.assert_array_equal(got, far)
    np.testing.assert_array_equal(got_cov, cov)


def test_the_vertices_gain_is_the_lines_derivative():
    rng = np.random.default_rng(1)
    ang = np.array([0.3, 2.4, 4.4])
    n = np.column_stack([np.cos(ang), np.sin(ang)])
    c = rng.normal(size=(3, 2)) * 5.0
    V, invs = _intersections(n, c)
    G = _vertex_gain(n, c, V, invs)
    h = 1e-7
    for i in range(3):
        for k in range(2):
            n2, c2 = n.copy(), c.copy()
            if k == 0:
                cs, sn = np.cos(h), np.sin(h)
                n2[i] = [cs * n[i, 0] - sn * n[i, 1], sn * n[i, 0] + cs * n[i, 1]]
            else:
                c2[i] = c[i] + h * n[i]
            num = (_intersections(n2, c2)[0] - V).ravel() / h
            np.testing.assert_allclose(G[:, 2 * i + k], num, atol=1e-5)
