"""Speed and quality measurements of Nimbus (scripts; run with ``python -m benchmark.<name>``)."""
