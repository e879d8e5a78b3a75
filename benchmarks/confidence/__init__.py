"""Confidence: whether the failure flag catches failed registrations and spares good ones."""
