"""The benches of `dimenet bench`, above the simulator, ingest and evaluation they measure: latency
(the rectifier against OpenCV's PnP), ingest (photos against the renderer's truth, scored by
ingest_score), fuzz (hostile input), stream (`dimenet rectify --points` throughput and memory) and streams (a simulated
recording scored per frame, temporal and with the gyroscope)."""
