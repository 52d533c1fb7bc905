"""iXblue Hydrins INS protocols: NMEA (PHINS standard) and STDBIN, and the canonical NavRecord."""
