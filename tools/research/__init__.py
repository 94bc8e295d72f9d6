"""Probes for research questions; no command imports them."""
