"""The triangle pipeline (visvec.pipeline.triangle): tracking, the rolling shutter taken
out frame to frame, refused rows."""

from dataclasses import replace

import numpy as np

from visvec.bench.codecs import mp4v
from visvec.data import Frame, Status
from visvec.detect import TriangleDetector
from visvec.geometry import project_target
from visvec.pipeline import TrianglePipeline
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene
from visvec.sim.simulate import random_attitudes

from conftest import attitudes


def test_rolling_shutter_is_taken_out_while_tracking(rig640):
    """A rolling-shutter webcam (25 ms readout) on a platform turning at 20 deg/s: the
    triangle is sheared between its rows and the yaw reads low by more than a sigma on
    average; with the rig's readout_ms the edge points are taken back to the centre
    row's exposure using the rate of the last two frames (the second frame: detected
    again with the rate from its own first pass), and the errors are the sensor's own
    again. The first frame has no rate: it says so, and its sigma covers the platform's
    max_rate_dps."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline

    w_lab = np.radians([0.0, 0.0, 20.0])  # a yaw turn about n3
    frames, truth = [], []
    for k in range(20):
        e = np.array([0.3 + w_lab[2] * k / 30.0, np.radians(2.0), np.radians(-1.0)])
        R = euler_to_matrix(*e)
        img = render_frame(rig640, R, Scene(), 900 + k, 25.0, R.T @ w_lab)
        frames.append(Frame(k, k / 30.0, img))
        truth.append(np.degrees(e))

    def run(readout_ms, shear=True):
        # shear False: no readout estimated from the frames, the shear as it is
        rig = replace(rig640, readout_ms=readout_ms, max_rate_dps=20.0)
        pipe = TrianglePipeline(rig, check_shutter=shear)
        rows = [pipe.process(f) for f in frames]
        z = [
            (r.euler_deg - t) / r.sigma_deg if r.ok else np.full(3, np.nan)
            for r, t in zip(rows, truth, strict=True)
        ]
        return np.array(z), rows

    z_raw, _ = run(0.0, shear=False)
    z_fix, rows = run(25.0)
    assert np.all(np.isfinite(z_fix))  # every frame ok
    assert np.nanmean(z_raw[3:, 0]) < -1.0  # sheared: the yaw biased low
    assert abs(np.mean(z_fix[1:, 0])) < 0.5 and np.abs(z_fix[1:]).max() < 3.0
    uncorrected = [k for k, r in enumerate(rows) if "rolling_shutter_uncorrected" in r.warnings]
    assert uncorrected == [0]
    # the first frame's sigma is widened by the unknown rate, and covers its error
    assert rows[0].sigma_deg[0] > 2.0 * np.median([r.sigma_deg[0] for r in rows[1:]])
    assert np.abs(z_fix[0]).max() < 3.0


def test_rolling_shutter_readout_sigma_is_carried_into_the_rows(rig640):
    """A readout measured 5 ms short (20 for 25, as `calibrate readout` may find it one
    sigma off) on a platform turning at 10 deg/s while tilting at 4 deg/s: taken as
    exact, the correction leaves a shear that puts pitch rows up to 4 sigma off (error/
    sigma RMS 1.5); given with its 1-sigma of 5 ms ([camera] readout_sigma_ms), the
    vertices' covariance carries what that uncertainty leaves and the rows' sigma is
    honest again."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline
    from visvec.rotations import expmap, matrix_to_euler

    w_b = np.radians([3.0, -3.0, 10.0])  # body rate, deg/s
    R0 = euler_to_matrix(0.3, np.radians(2.0), np.radians(-1.0))
    frames, truth = [], []
    for k in range(20):
        R = R0 @ expmap(w_b * k / 30.0)
        frames.append(Frame(k, k / 30.0, render_frame(rig640, R, Scene(), 900 + k, 25.0, w_b)))
        truth.append(np.degrees(matrix_to_euler(R)))

    def run(sigma_ms):
        rig = replace(
            rig640,
            readout_ms=20.0,
            readout_sigma_ms=sigma_ms,
            max_rate_dps=12.0,
            max_tilt_rate_dps=5.0,  # the platform's bounds
        )
        pipe = TrianglePipeline(rig)
        rows = [pipe.process(f) for f in frames]
        assert all(r.ok for r in rows)
        # tracking, each frame's rate from the two before it (the acquisition's first
        # two frames are other tests' subject)
        pairs = zip(rows[2:], truth[2:], strict=True)
        z = np.array([(r.euler_deg - t) / r.sigma_deg for r, t in pairs])
        return np.abs(z).max(), np.sqrt(np.mean(z**2, axis=0))

    z_max, z_rms = run(0.0)
    assert z_max > 3.5 and z_rms[1] > 1.3  # confident wrong answers
    z_max, z_rms = run(5.0)
    assert z_max < 3.25 and np.all(z_rms < 1.15)


def test_still_frames_need_no_rate_and_keep_their_sigma(rig640):
    """`calibrate zero-tilt` runs on still frames: a rolling-shutter rig neither warns
    nor widens their sigma there, and gives the global-shutter rig's attitude. A frame
    without a rate (not known to be still) weighs its vertices with the shear an
    unknown rate could make: nearly the same attitude, with a wider sigma."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline

    img = render_frame(rig640, euler_to_matrix(0.7, 0.0, 0.0), Scene(), 77)
    rolling = replace(rig640, readout_ms=25.0)
    plain = TrianglePipeline(rig640).process(Frame(0, 0.0, img))
    still = TrianglePipeline(rolling, still=True).process(Frame(0, 0.0, img))
    moving = TrianglePipeline(rolling).process(Frame(0, 0.0, img))
    assert plain.ok and still.ok and moving.ok
    np.testing.assert_allclose(still.euler_deg, plain.euler_deg, atol=1e-9)
    np.testing.assert_allclose(still.sigma_deg, plain.sigma_deg, rtol=1e-9)
    assert "rolling_shutter_uncorrected" not in still.warnings + plain.warnings
    assert "rolling_shutter_uncorrected" in moving.warnings
    # the unknown rate in the vertices' covariance: another weighting of the same
    # vertices, within half the wider sigma (over 20 noise draws of this attitude the two
    # differ by a median 0.3 of it, at most 1.1)
    assert np.all(np.abs(moving.euler_deg - plain.euler_deg) < 0.5 * moving.sigma_deg)
    assert np.all(moving.sigma_deg > plain.sigma_deg)


def test_rolling_shutter_of_a_camera_off_the_axis_is_taken_out_while_tracking(rig640):
    """The camera 250 mm off the rotation axis: turning also moves it, and its
    translation during the readout shears the triangle by as much as the rotation. With
    the lever arm in the correction every tracked frame is ok and within 3 sigma, the
    yaw unbiased (the rotation alone left 13 of 60 frames refused and a 1.2-sigma bias)."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline

    mount = replace(rig640.mount, position_mm=np.array([250.0, 0.0, 150.0]))
    rig = replace(rig640, mount=mount, readout_ms=25.0)
    w = np.radians(20.0)
    pipe = TrianglePipeline(rig)
    z = []
    for k in range(20):
        e = np.array([0.3 + w * k / 30.0, np.radians(2.0), np.radians(-1.0)])
        R = euler_to_matrix(*e)
        img = render_frame(rig, R, Scene(), 700 + k, 25.0, R.T @ [0.0, 0.0, w])
        row = pipe.process(Frame(k, k / 30.0, img))
        assert row.ok, (k, row.warnings)
        z.append((row.euler_deg - np.degrees(e)) / row.sigma_deg)
    z = np.array(z[1:])  # the first frame is uncorrected (no rate yet)
    assert abs(z[:, 0].mean()) < 0.5 and np.abs(z).max() < 3.0


def test_the_pixel_fit_takes_a_rolling_shutter_out_too(rig640, monkeypatch):
    """refine = "pixels" on a rolling-shutter webcam turning at 12-20 deg/s: the first
    frame (no rate yet) keeps the lines; every tracked frame after it is the pixel
    fit's, its pixels taken to the centre row's exposure with the rate: error over
    sigma of unit RMS, the yaw unbiased, and more precise than the lines. Without
    taking them there the rows are refused or off (the yaw's error over sigma RMS
    above 1.5: the shear's bias, whose sign follows the turn's)."""
    from visvec.data import Frame
    from visvec.detect import photometric
    from visvec.detect import triangle as T
    from visvec.pipeline import TrianglePipeline

    base = replace(rig640, readout_ms=25.0)
    runs = []
    for seed, dps in ((1, 20.0), (2, -16.0), (3, 12.0)):
        w = np.radians(dps)
        frames, truth = [], []
        for k in range(12):
            e = np.array([0.3 * seed + w * k / 30.0, np.radians(2.0), np.radians(-1.0)])
            R = euler_to_matrix(*e)
            img = render_frame(base, R, Scene(), 100 * seed + k, 25.0, R.T @ [0.0, 0.0, w])
            frames.append(Frame(k, k / 30.0, img))
            truth.append(np.degrees(e))
        runs.append((frames, truth))
    taken = []

    def spy(*a):
        pf = photometric.refine(*a)
        taken.append(pf.ok and a[5] is not None and a[6] is not None)
        return pf

    def run(refine, all_ok=True):
        err, sig = [], []
        for frames, truth in runs:
            pipe = TrianglePipeline(replace(base, detect=replace(base.detect, refine=refine)))
            rows = [pipe.process(f) for f in frames]
            assert all(r.ok for r in rows) or not all_ok
            assert rows[0].warnings == ("rolling_shutter_uncorrected",)
            for r, t in list(zip(rows, truth, strict=True))[1:]:
                if r.ok:
                    err.append(r.euler_deg - t)
                    sig.append(r.sigma_deg)
        err, sig = np.array(err), np.array(sig)
        return err / sig, err, sig

    monkeypatch.setattr(T, "refine", spy)
    _, err_l, sig_l = run("lines")
    assert not taken  # the lines never call it
    z, err, sig = run("pixels")
    assert len(taken) >= 33 and sum(taken) >= 33  # the tracked frames: fitted, with the rate
    assert np.abs(z).max() < 4.0 and np.all(np.sqrt(np.mean(z**2, axis=0)) < 1.3)
    assert abs(z[:, 0].mean()) < 0.5
    assert np.all(np.median(sig / sig_l, axis=0) < 0.9)
    assert np.all(np.sqrt(np.mean(err**2, axis=0)) < np.sqrt(np.mean(err_l**2, axis=0)))
    # the pixels left where the rows see them: refused by the gate, or off
    taken.clear()
    monkeypatch.setattr(photometric, "_unrolled", lambda xy, rows, camera, roll: xy)
    z_off, _, _ = run("pixels", all_ok=False)
    refused = 33 - len(z_off)
    yaw_rms = float(np.sqrt(np.mean(z_off[:, 0] ** 2)))
    assert refused >= 10 or yaw_rms > 1.5, (refused, yaw_rms)


def test_a_turn_faster_than_the_rate_bounds_is_acquired_at_once(rig640):
    """Turning at 20 deg/s with the apex along the image columns and tilting at 2.6 deg/s
    (the rig says 10 and 2 at most): the first frame, its vertices weighed with the shear
    a rate within the bounds could make, is within 3 sigma (before that covariance was
    in the fit's weights, its chi-square refused it and tracking started at the second
    frame; before the second frame took its rate from a refused first one, every frame
    was a refused first one, 8 of 10)."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline
    from visvec.sim.simulate import body_rates

    rig = replace(rig640, readout_ms=25.0)
    rate = np.radians([20.0, -2.6, -0.6])  # yaw, pitch, roll per second
    eul = [np.radians([-83.3, 0.15, 3.0]) + rate * k / 30.0 for k in range(8)]
    R = np.array([euler_to_matrix(*e) for e in eul])
    w_b = body_rates(R, 1.0 / 30.0)
    pipe = TrianglePipeline(rig)
    rows = [
        pipe.process(Frame(k, k / 30.0, render_frame(rig, R[k], Scene(), 73000 + k, 25.0, w_b[k])))
        for k in range(8)
    ]
    assert rows[0].ok and rows[0].warnings == ("rolling_shutter_uncorrected",)
    assert all(r.ok and r.warnings == () for r in rows[1:])
    z = [(r.euler_deg - np.degrees(e)) / r.sigma_deg for r, e in zip(rows, eul, strict=True)]
    assert np.abs(z).max() < 3.0


def test_rolling_shutter_read_bottom_up_is_taken_out_too(rig640):
    """A negative readout (the last row read first, as with a flipped image): the shear
    and the yaw bias change sign, and the correction takes them out the same way."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline

    w = np.radians(20.0)
    frames, truth = [], []
    # 12 frames turning one way, then 12 turning back
    for k in range(24):
        rate = w if k < 12 else -w
        e = np.array([0.3 + w * min(k, 22 - k) / 30.0, np.radians(2.0), np.radians(-1.0)])
        R = euler_to_matrix(*e)
        img = render_frame(rig640, R, Scene(), 950 + k, -25.0, R.T @ [0, 0, rate])
        frames.append(Frame(k, k / 30.0, img))
        truth.append(np.degrees(e))

    def yaw_z(readout_ms, shear=True, n=12):
        # shear False: no readout estimated from the frames
        pipe = TrianglePipeline(replace(rig640, readout_ms=readout_ms), check_shutter=shear)
        rows = [pipe.process(f) for f in frames[:n]]
        assert all(r.ok for r in rows[1:])
        z = [(r.euler_deg[0] - t[0]) / r.sigma_deg[0] for r, t in zip(rows, truth, strict=False)]
        return np.array(z[1:]), pipe

    assert yaw_z(0.0, shear=False)[0].mean() > 1.0  # uncorrected: biased high
    z, _ = yaw_z(-25.0)
    assert abs(z.mean()) < 0.6 and np.abs(z).max() < 3.0
    # the rig says global shutter: the frames' own estimate has the readout's sign once
    # the turn goes back (one way only, a shear is not told apart from the camera's
    # principal point a few px off)
    _, pipe = yaw_z(0.0, n=24)
    k, sigma = pipe.shear.readout_ms()
    assert k < -2.0 * sigma and abs(k + 25.0) < 2.0 * sigma, (k, sigma)


def test_rolling_shutter_rate_only_from_related_frames(rig640):
    """The rate comes from the last two ok frames when they are a turn (below
    MAX_RATE_DPS), not from two unrelated frames of a folder (level frames 30 deg apart)
    nor from stale ones."""
    from visvec.pipeline.triangle import MAX_RATE_DPS, TrianglePipeline

    pipe = TrianglePipeline(replace(rig640, readout_ms=25.0))
    turn = np.radians(10.0) / 30.0  # 10 deg/s at 30 fps
    pipe._recent = [(0.0, euler_to_matrix(0.2, 0, 0)), (1 / 30, euler_to_matrix(0.2 + turn, 0, 0))]
    np.testing.assert_allclose(pipe._camera_rate(2 / 30), [0, 0, np.radians(10.0)], atol=1e-9)
    assert pipe._camera_rate(1.0) is None  # the last ok frame is stale
    jump = np.radians(30.0)
    assert np.degrees(jump * 30) > MAX_RATE_DPS
    pipe._recent = [(0.0, euler_to_matrix(0.2, 0, 0)), (1 / 30, euler_to_matrix(0.2 + jump, 0, 0))]
    assert pipe._camera_rate(2 / 30) is None


def test_a_tracked_prediction_far_off_goes_to_the_full_search(rig640):
    """The platform jumps 30 px between frames (defocused to 2 px): the tracked fit's
    lines still move after re-centring, so the frame is searched afresh instead of being
    reported from a fit that had not settled (it was, with a vertex 3.7 sigma off)."""
    atts = attitudes(8, 11)
    det = TriangleDetector(rig640)
    sc = Scene(blur_sigma_px=2.0)
    for j in range(5):
        assert det.detect(render_frame(rig640, atts[1], sc, rng=910 + j)).status is Status.OK
    assert np.abs(det._last_points - project_target(rig640, atts[2])).max() > 20.0
    d = det.detect(render_frame(rig640, atts[2], sc, rng=920))
    assert d.status is Status.OK
    assert not det.last_was_tracked
    e = d.points_n - rig640.camera.undistort(project_target(rig640, atts[2]))
    assert np.all(np.abs(e.ravel() / np.sqrt(np.diag(d.cov_n))) < 3.0)


def test_tracking_follows_a_lens_that_refocuses(rig640):
    """Tracked frames used to keep the blur widths of the last cold frame: after the
    lens went from 0.6 to 1.5 px of blur mid-run, the profiles (3 old widths long) cut
    the new blur and the tilts' error/sigma RMS rose to 1.3 (one row at 5.5 sigma in
    100). Each tracked frame now measures the widths on its own profiles and, when they
    are off by more than WIDTH_CHANGE, measures them afresh: the frame stays tracked,
    ok, and its vertices' error/sigma stays about 1."""
    det = TriangleDetector(rig640)
    eul = random_attitudes(300, 4.0, np.random.default_rng(6), "sweep")[:12]
    z = []
    for k, e in enumerate(eul):
        R = euler_to_matrix(*e)
        img = render_frame(rig640, R, Scene(blur_sigma_px=0.6 if k < 4 else 1.5), rng=700 + k)
        d = det.detect(img)
        assert d.status is Status.OK, (k, d.reason)
        assert det.last_was_tracked or k == 0
        if k >= 4:
            err = d.points_n - rig640.camera.undistort(project_target(rig640, R))
            z.append(err.ravel() / np.sqrt(np.diag(d.cov_n)))
        if k == 3:
            assert np.median(det._last_width) < 1.0, det._last_width
    assert 1.4 < np.median(det._last_width) < 1.9, det._last_width
    assert np.sqrt(np.mean(np.square(z))) < 1.4


def test_pipeline_turns_an_internal_error_into_a_refused_row(rig640, monkeypatch):
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline

    pipe = TrianglePipeline(rig640)

    def boom(image, omega_c=None):
        raise RuntimeError("bug")

    monkeypatch.setattr(pipe.detector, "detect", boom)
    row = pipe.process(Frame(0, 0.0, np.zeros((480, 640), np.uint8)))
    assert row.status is Status.REJECTED and "internal_error" in row.warnings
    assert "bug" in pipe.last_error


def test_a_codecs_correlated_errors_along_the_edges_widen_the_sigma(rig320):
    """mp4v's block errors are shared by neighbouring edge profiles: the run learns
    their correlation and widens the lines' covariance by the long-run variance
    (1.4 on these 40 frames at 320x240, 1.8 on a longer recording); the same frames
    stored losslessly leave it exactly as it was."""
    eul = random_attitudes(40, 5.0, np.random.default_rng(31), "sweep")
    frames = [render_frame(rig320, euler_to_matrix(*e), Scene(), rng=3100 + k)
              for k, e in enumerate(eul)]  # fmt: skip
    factors, notes = {}, {}
    for name, images in (("png", frames), ("mp4v", mp4v(frames))):
        pipe = TrianglePipeline(rig320)
        rows = [pipe.process(Frame(i, i / 30.0, im)) for i, im in enumerate(images)]
        assert sum(r.ok for r in rows) >= 35, name
        factors[name] = pipe.detector.correlation.factor
        notes[name] = " ".join(pipe.notes())
    assert factors["png"] == 1.0
    assert 1.2 < factors["mp4v"] < 2.6, factors
    assert "codec" not in notes["png"] and "codec" in notes["mp4v"]


def test_the_pixel_fit_is_set_aside_on_frames_of_an_inter_frame_codec(rig320):
    """Frames that say they came through mp4v (Frame.codec "FMP4", as a video file's
    reader names it) are measured by the edge lines on a pixel-fit rig: the same rows
    as the lines' rig, and a closing note that says so; the same frames without a codec
    go through the pixel fit (other rows). Motion-JPEG's frames keep it."""
    eul = random_attitudes(12, 5.0, np.random.default_rng(31), "sweep")
    frames = [render_frame(rig320, euler_to_matrix(*e), Scene(), rng=3100 + k)
              for k, e in enumerate(eul)]  # fmt: skip
    images, codec = mp4v(frames, with_codec=True)
    assert codec == "FMP4"
    pixels = replace(rig320, detect=replace(rig320.detect, refine="pixels"))

    def run(rig, codec):
        pipe = TrianglePipeline(rig)
        rows = [pipe.process(Frame(i, i / 30.0, im, codec=codec)) for i, im in enumerate(images)]
        assert sum(r.ok for r in rows) >= 10
        return rows, pipe.notes()

    lines, _ = run(rig320, codec)
    set_aside, notes = run(pixels, codec)
    fitted, notes_fitted = run(pixels, "")
    mjpeg, notes_mjpeg = run(pixels, "MJPG")
    both = [k for k in range(len(images)) if lines[k].ok and fitted[k].ok]
    for k in range(len(images)):
        assert set_aside[k].status is lines[k].status
        if lines[k].ok:
            assert np.array_equal(set_aside[k].euler_deg, lines[k].euler_deg)
            assert np.array_equal(set_aside[k].sigma_deg, lines[k].sigma_deg)
    assert max(np.abs(fitted[k].euler_deg - lines[k].euler_deg).max() for k in both) > 1e-4
    assert all(np.array_equal(mjpeg[k].euler_deg, fitted[k].euler_deg) for k in both)
    (note,) = [n for n in notes if "FMP4" in n]
    assert "set aside" in note and "edge lines" in note
    assert not any("FMP4" in n or "set aside" in n for n in notes_fitted + notes_mjpeg)


def test_rows_through_an_inter_frame_codec_say_their_sigma_is_not_measured(rig320):
    """Frames of a codec that predicts frames from earlier ones (h264, FMP4): each ok
    row carries inter_frame_codec while the rig's [detect] sigma_scale is 1 (not
    measured through the stream); with a measured sigma_scale, or through Motion-JPEG
    or with no codec named, none does."""
    eul = random_attitudes(6, 5.0, np.random.default_rng(31), "sweep")
    images = [render_frame(rig320, euler_to_matrix(*e), Scene(), rng=3100 + k)
              for k, e in enumerate(eul)]  # fmt: skip
    measured = replace(rig320, detect=replace(rig320.detect, sigma_scale=1.4))
    for rig, codec, warned in ((rig320, "h264", True), (rig320, "FMP4", True),
                               (measured, "h264", False), (rig320, "MJPG", False),
                               (rig320, "", False)):  # fmt: skip
        pipe = TrianglePipeline(rig)
        rows = [pipe.process(Frame(i, i / 30.0, im, codec=codec)) for i, im in enumerate(images)]
        assert sum(r.ok for r in rows) == len(images), codec
        assert all(("inter_frame_codec" in r.warnings) == warned for r in rows), (codec, rig)
        assert any("sigma_scale measured them" in n for n in pipe.notes()) == warned
        # a lines rig whose sigma_scale was measured has nothing to be told
        assert any(codec and codec in n for n in pipe.notes()) == warned


def test_a_run_through_a_codec_is_told_so_at_its_end(rig320):
    """The closing note, when the learned correlation says the frames went through a
    codec; with the pixel fit, that it is not honest there."""
    for refine in ("lines", "pixels"):
        pipe = TrianglePipeline(replace(rig320, detect=replace(rig320.detect, refine=refine)))
        assert not any("codec" in n for n in pipe.notes())
        pipe.detector.correlation.factor = 1.9  # as mp4v's frames teach it
        (note,) = [n for n in pipe.notes() if "codec" in n]
        assert "1.9x" in note and "codec" in note
        assert ('refine = "lines"' in note) == (refine == "pixels")


def test_a_frame_read_late_keeps_its_values_and_is_warned(rig640):
    """A live frame that waited before it was read (Frame.read_late set by its
    reader): the same values, ok, warned read_late; a refused one is not warned."""
    import threading

    img = render_frame(rig640, euler_to_matrix(*np.radians([30.0, 1.0, -2.0])), Scene(), 5, 25.0)
    flag = threading.Event()
    on_time = TrianglePipeline(rig640).process(Frame(0, 0.0, img, read_late=flag))
    flag.set()
    late = TrianglePipeline(rig640).process(Frame(0, 0.0, img, read_late=flag))
    assert on_time.ok and "read_late" not in on_time.warnings
    assert late.ok and late.warnings == on_time.warnings + ("read_late",)
    np.testing.assert_array_equal(late.euler_deg, on_time.euler_deg)
    blank = TrianglePipeline(rig640).process(Frame(1, 0.0, np.zeros_like(img), read_late=flag))
    assert not blank.ok and "read_late" not in blank.warnings
