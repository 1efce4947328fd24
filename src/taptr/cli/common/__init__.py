"""What the commands of `taptr.cli` share: option helpers, checks, queries and run records.

Every module of `taptr.cli` itself is one command (registered from `taptr.cli.main`'s
``COMMANDS``); the modules here are not commands.
"""
