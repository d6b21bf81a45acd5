"""visvec: camera attitude sensor for air-bearing spacecraft simulators.

The public API is in :mod:`visvec.api`.
"""

import os as _os

# FFmpeg's own messages ("[mjpeg @ 0x...] No JPEG data found in image") name no frame
# and come before visvec's row for that frame, which does; they are kept quiet unless
# the environment asks for them (OPENCV_FFMPEG_LOGLEVEL=32 shows them). Set before
# OpenCV is first imported, which reads it then.
_os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

__version__ = "0.1.0"
