"""Test doubles and reference implementations shared by the tests (never imported by ps_lab)."""
