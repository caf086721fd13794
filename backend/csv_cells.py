"""Spreadsheet-safe CSV cells: OWASP's CSV-injection rule.

A spreadsheet (Excel, LibreOffice, Google Sheets) runs a cell starting with ``=``, ``+``,
``-`` or ``@`` as a formula, and a leading tab or carriage return lets such a cell hide
behind whitespace; a catalogue record written by anyone with staff rights could thus make
a reader's spreadsheet call ``=HYPERLINK("http://evil.example", ...)`` or worse. OWASP's
rule (https://owasp.org/www-community/attacks/CSV_Injection): prefix such a cell with a
single quote, which spreadsheets read as "this is text" and do not show.

Only text values are escaped: numbers (``-1.5`` in ``height_mm``) are real numeric values,
written as numbers, so sums and sorts in the spreadsheet keep working.
"""

from __future__ import annotations

FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def safe_cell(value: object) -> object:
    """``value`` as a CSV cell a spreadsheet will not run: text starting with a formula
    character gets a leading ``'``; numbers, booleans and ``None`` are left as they are."""
    if isinstance(value, str) and value.startswith(FORMULA_STARTS):
        return "'" + value
    return value


def safe_row(row: dict) -> dict:
    """Every cell of ``row`` made safe (see ``safe_cell``)."""
    return {name: safe_cell(value) for name, value in row.items()}
