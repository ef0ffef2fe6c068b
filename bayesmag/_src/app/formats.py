"""The export formats ``bayesmag export --format`` writes, and their file suffixes (checked by the config too)."""

__all__ = ["FORMATS"]

#: format name -> suffix of the file written next to the calibration (``calibration<suffix>``)
FORMATS = {"json": ".export.json", "c-header": ".h", "magcal": ".magcal.json", "px4": ".params", "ardupilot": ".parm"}
