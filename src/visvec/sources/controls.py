"""A USB camera's exposure, gain and focus: set from the rig's ``[camera]`` keys, read
back, and said at the start of a run.

Auto-exposure and autofocus both move the measurement while it runs (a brighter frame
shifts a blurred edge's threshold crossing; a refocus changes the image's scale), so a
run says when either stays on. OpenCV passes the values to the driver unchanged; what
the camera kept is what is read back."""

from __future__ import annotations

import cv2

from visvec.rig import CameraControls

# CAP_PROP_AUTO_EXPOSURE's values: V4L2's menu (1 manual, 3 aperture priority) first,
# then the 0.25 / 0.75 other backends use
AUTO_EXPOSURE_VALUES = {False: (1.0, 0.25), True: (3.0, 0.75)}


def _close(got: float, want: float) -> bool:
    return abs(got - want) <= max(1e-6, 0.01 * abs(want))


def _auto_exposure_on(cap) -> bool | None:
    v = cap.get(cv2.CAP_PROP_AUTO_EXPOSURE)
    if any(_close(v, x) for x in AUTO_EXPOSURE_VALUES[True]):
        return True
    if any(_close(v, x) for x in AUTO_EXPOSURE_VALUES[False]):
        return False
    return None  # the backend does not say


def _autofocus_on(cap) -> bool | None:
    v = cap.get(cv2.CAP_PROP_AUTOFOCUS)
    if _close(v, 1.0):
        return True
    if _close(v, 0.0):
        return False
    return None


def _onoff(v: bool | None) -> str:
    return "unknown" if v is None else ("on" if v else "off")


def apply_controls(cap, c: CameraControls, name: str) -> list[str]:
    """Set what ``c`` names on an open capture; the warnings for the controls the
    camera refused, each naming the control and the value it kept. An exposure (focus)
    without auto_exposure (auto_focus) turns the automatic one off first."""
    warnings: list[str] = []

    def refused(key: str, want: str, kept: str) -> None:
        warnings.append(f"{name}: refused [camera] {key} = {want}; it kept {kept}")

    auto_exp = c.auto_exposure if c.auto_exposure is not None else (
        False if c.exposure is not None else None)  # fmt: skip
    if auto_exp is not None:
        for v in AUTO_EXPOSURE_VALUES[auto_exp]:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, v)
            if _auto_exposure_on(cap) is auto_exp:
                break
        else:
            refused(
                "auto_exposure",
                str(auto_exp).lower(),
                f"auto-exposure {_onoff(_auto_exposure_on(cap))}",
            )
    auto_foc = c.auto_focus if c.auto_focus is not None else (
        False if c.focus is not None else None)  # fmt: skip
    if auto_foc is not None:
        cap.set(cv2.CAP_PROP_AUTOFOCUS, 1.0 if auto_foc else 0.0)
        if _autofocus_on(cap) is not auto_foc:
            refused("auto_focus", str(auto_foc).lower(), f"autofocus {_onoff(_autofocus_on(cap))}")
    for key, prop, want in (
        ("exposure", cv2.CAP_PROP_EXPOSURE, c.exposure),
        ("gain", cv2.CAP_PROP_GAIN, c.gain),
        ("focus", cv2.CAP_PROP_FOCUS, c.focus),
    ):
        if want is None:
            continue
        cap.set(prop, float(want))
        got = cap.get(prop)
        if not _close(got, want):
            refused(key, f"{want:g}", f"{got:g}")
    return warnings


def describe_controls(cap, name: str) -> tuple[str, list[str]]:
    """What the camera runs with (one line), and the warnings for an auto-exposure or
    autofocus that is on."""
    ae, af = _auto_exposure_on(cap), _autofocus_on(cap)
    w = cap.get(cv2.CAP_PROP_FRAME_WIDTH)
    h = cap.get(cv2.CAP_PROP_FRAME_HEIGHT)
    fps = cap.get(cv2.CAP_PROP_FPS)
    line = (
        f"{name} runs at {w:g}x{h:g}, {fps:g} fps; exposure {cap.get(cv2.CAP_PROP_EXPOSURE):g} "
        f"(auto-exposure {_onoff(ae)}), gain {cap.get(cv2.CAP_PROP_GAIN):g}, focus "
        f"{cap.get(cv2.CAP_PROP_FOCUS):g} (autofocus {_onoff(af)})"
    )
    warnings = []
    if ae:
        warnings.append(
            f"{name}: auto-exposure is on: the image's brightness, and with it where a "
            "blurred edge or spot is measured, can change during the run; set [camera] "
            "auto_exposure = false and an exposure"
        )
    if af:
        warnings.append(
            f"{name}: autofocus is on: a refocus changes the image's scale and sharpness "
            "during the run; set [camera] auto_focus = false and a focus"
        )
    return line, warnings
