"""The HTTP side: the FastAPI app (:mod:`.app`), one router per resource (calibrations,
kinematic files, the operator's answers of a run without motion capture, metrics), the
request guard, the bounded uvicorn server and the operator console."""
