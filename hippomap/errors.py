"""Exceptions raised by hippomap. Every message names the offending value or line."""


class HippomapError(Exception):
    """Base class of hippomap's own errors."""


class InputError(HippomapError, ValueError):
    """Bad input: NaN/infinite odometry, non-increasing timestamps, malformed files, bad images."""
