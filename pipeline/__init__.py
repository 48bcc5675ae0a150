"""Pure signal processing for knee flexion from thigh and shank IMUs.

numpy/scipy in, dataclasses out: no web, no database, no global state.
The entry point for a whole session is :func:`pipeline.session.process_session`.
"""

ALGORITHM_VERSION = "0.1.0"
