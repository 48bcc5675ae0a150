"""gaitmon's Python client (``gaitmon.client``) for app backends and research scripts."""
