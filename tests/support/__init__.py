"""Helpers the tests share: scenes, a headless browser, tiny models, triplane files."""
