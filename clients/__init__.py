"""Clients of the cadreg service; they import only the service's wire modules (schemas, codec, errors, zenoh_wire).

    clients.http          Client, AsyncClient (httpx): localize, sites, site, health, ready, metrics_text; pose_of
    clients.zenoh_client  ZenohClient (query cadreg/<site>/localize) and PoseStream (frames/poses stream mode)
    clients.errors        one exception class per wire code (InvalidFrame, UnknownSite, Overloaded, ...)
    clients.core          ClientCore: what every transport shares (frame encoding, folder cache, top_k, retries)
    clients.retry         RetryPolicy (backoff + jitter, Retry-After), ClientPause, RetryLoop (call / acall)
    clients.frames        EncodedFrame: a cadreg Frame or a recorded-frames folder entry as wire parts
    clients.load          load tester core (closed/open loop), clients.load_cli is `cadreg load`
    clients.report        load test tables and PNGs
"""
