"""The HTTP service: FastAPI app, auth, storage, background processing. Calls ``pipeline``."""
