"""The cadreg registration service: HTTP (FastAPI) and zenoh front ends over one pool of worker processes.

Wire modules (the only ones the clients import): `schemas` (FrameMeta, ErrorBody, response models), `codec`
(frame parts, the zenoh envelope, result JSON), `errors` (one table from error class to HTTP status and code),
`zenoh_wire` (zenoh keys, session config, result/error encodings).
Runtime: `settings` (Settings, prefix CADREG_), `registry` (sites and versions, atomic swaps), `pool` + `worker`
(processes, bounded queue, deadlines, crash recovery), `runtime` (Service: what both front ends call),
`http_app` (create_app), `zenoh_server`, `metrics`, `cli` (`cadreg serve`).
"""
