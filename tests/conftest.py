"""The suite runs on one CPU device per worker process (``pytest -n 2`` already keeps both
cores busy), where ``import tracklab`` alone would make one per core: splitting each chunk
over devices costs compile time and no test needs it, except the device-count test, which
starts its own processes with 1, 2 and 4 devices."""

import os

if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=1").strip()
