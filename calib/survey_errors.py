"""The error every survey step raises (:mod:`maglog.calib.survey` and the modules it calls).

A :class:`SurveyError` carries one line that says what is wrong and where (file, time, line),
and the command line prints it as ``maglog: error: ...`` without a traceback.
"""

__all__ = ["SurveyError"]


class SurveyError(ValueError):
    """A card, base-station file or setting the survey path cannot use (one-line message)."""
