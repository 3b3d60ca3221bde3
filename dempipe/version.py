"""dempipe's version, kept apart so that any layer can name it without importing the
front door."""

__version__ = "0.1.0"
