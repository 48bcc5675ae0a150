"""Background processing of completed sessions.

``queue`` hands a session to whichever runner is configured, ``process`` claims and processes sessions (shared by
every runner), ``embedded`` is the in-process thread used with SQLite, ``worker`` is the procrastinate app used
with PostgreSQL (``gaitmon worker``, any number of machines).
"""
