"""Localization: from a query to an answer (retrieval, fusion, verification)."""
