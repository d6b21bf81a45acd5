"""Frame sources: iterators of :class:`visvec.data.Frame` with times."""

from visvec.sources.folder import FolderSource
from visvec.sources.open import open_source
from visvec.sources.synthetic import SyntheticSource
from visvec.sources.video import VideoSource

__all__ = ["FolderSource", "SyntheticSource", "VideoSource", "open_source"]
