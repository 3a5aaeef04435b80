"""Real-robot adapter package (ABB IRC5 side); submodules are imported on demand so this stays import-light."""
