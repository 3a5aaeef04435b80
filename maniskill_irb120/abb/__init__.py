"""The real-robot side (ABB IRC5): wire protocol, client, safety envelope, emulated robot, RAPID interpreter.

Submodules are imported on demand, so importing this package stays light."""
