"""How the manual's reference pages are made from the code, so that they cannot drift.

scripts/gen_reference.py says where each page goes and writes them; this package makes them:

- cli.py: the command line page, every command and option of `flytrack` (the typer app in
  flytrack_host.cli, walked as click sees it).
- models.py: a pydantic model walked into sections of fields (type, default, unit, description,
  example), and the page of such a model.
- rig_rules.py: the rig file's page (flytrack_host.rig.RigConfig) and the rules file's
  (flytrack_host.actuation.rules.RuleSet), with their intros, hand-picked examples and output kinds.
- recording.py: every table of a recording and its columns (flytrack_host.recording.schema), with
  the notes below (TABLE_NOTES).
- common.py: what every page shares.
"""
