"""Wire format: topic names, message types, QoS, frame ids, encode/decode. The one place that defines it."""
