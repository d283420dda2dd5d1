"""The data layer's error type (defined in :mod:`diamond_sss.errors`, shared with the run-folder readers)."""

from diamond_sss.errors import DamagedFileError, DataError, data_error

__all__ = ["DamagedFileError", "DataError", "data_error"]
