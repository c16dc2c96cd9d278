-- A robot's times are kept between the first and the last instant RFC 3339 can write
-- (-009999-01-02T01:59:59Z and 9999-12-30T22:00:00Z), as the gateway now stores them: rows
-- stored before with times beyond (a clock sending 2^63-1) get the nearest bound, so that every
-- range of RFC 3339 times reaches them.
UPDATE events SET ts_ms = MAX(MIN(ts_ms, 253402207200000), -377705023201000)
    WHERE ts_ms NOT BETWEEN -377705023201000 AND 253402207200000;
UPDATE samples SET ts_ms = MAX(MIN(ts_ms, 253402207200000), -377705023201000)
    WHERE ts_ms NOT BETWEEN -377705023201000 AND 253402207200000;
UPDATE telemetry_batches SET max_ts_ms = MAX(MIN(max_ts_ms, 253402207200000), -377705023201000)
    WHERE max_ts_ms NOT BETWEEN -377705023201000 AND 253402207200000;
