"""Print the effect catalogue as a Markdown table."""

from rotcal.model.effects import table

print(table(), end="")
