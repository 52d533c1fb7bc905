"""Device protocols (sans-I/O codecs) and thin async transports (docs/architecture.md §5).

- :mod:`drivers.base` — DecoderStats, the Decoder protocol, DriverError, the kind Registry and
  ``create_from_config`` (a config's ``kind`` → an object).
- :mod:`drivers.hydrins` — the iXblue Hydrins INS: ``nmea_sentences`` (typed sentence records,
  field parsers, checksum), ``nmea_decode`` (sentence decoder, epoch assembler), ``nmea_encode``
  (PHINS standard block, ZDA); ``stdbin_format`` (STDBIN V2–V5 sizes, headers, block tables),
  ``stdbin_records`` (frames, answers, their NavRecord view), ``stdbin_decode``, ``stdbin_encode``;
  ``nav`` (the canonical NavRecord all produce), ``timeofday`` (dating time-of-day tags).
- :mod:`drivers.zf` — the profiler: ``codec`` (Packet, Profile, the ProfileCodec seam), ``zfp1``
  (the ZFP1 stand-in format), ``assembler`` (ProfileAssembler with loss/reorder accounting).
- :mod:`drivers.pps` — PPS edges, gpsd's labelling rule, kernel / serial-line / udp sources.
- :mod:`drivers.can` — python-can buses from config, host-stamped frames, event markers.
- :mod:`drivers.transport` — async transports yielding (bytes, host_ns): ``base`` (Transport,
  Chunk, TransportEvent), ``registry`` (the table by ``kind``, ``create_transport``), one module
  per transport: ``serial_port``, ``udp``, ``tcp``, ``udp_batch`` (with ``recvmmsg``).
- :mod:`drivers.capture.pcapng`, :mod:`drivers.capture.files` — captures and recorded files; :mod:`drivers.timing`
  — device clock drift/offset/jitter against receive stamps.
"""
