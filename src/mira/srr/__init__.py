"""Semantic reward reframing (SRR, section 4.4): from diagnostic evidence to checked program edits."""
