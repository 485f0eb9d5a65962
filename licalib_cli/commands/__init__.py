"""Command implementations: parse options, one library call, render. No numerics here."""
