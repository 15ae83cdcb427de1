#!/bin/sh
# `loopwatch serve` in this container's role (LOOPWATCH_ROLE: api, ingest, scheduler, all),
# on port 8000 of every interface; with the plant file LOOPWATCH_PLANT_FILE when it is set,
# otherwise the simulated demo plant.
set -eu
if [ -n "${LOOPWATCH_PLANT_FILE:-}" ]; then
    exec loopwatch serve --host 0.0.0.0 --port 8000 --config "$LOOPWATCH_PLANT_FILE" "$@"
fi
exec loopwatch serve --host 0.0.0.0 --port 8000 "$@"
