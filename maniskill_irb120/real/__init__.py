"""The real-robot side: the wire protocol to our RAPID server on an ABB IRC5 (and, to come, its client)."""
