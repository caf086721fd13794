"""Shared fixtures. Package-specific fixtures live in the conftest of each test folder."""
