"""Studies: many population runs and the comparisons between them as one resumable unit (``ocv2 study``).

``spec`` reads and checks study files, ``runner`` trains, cross-plays and keeps the study directory's
state, ``report`` writes the report beside the paper's numbers.
"""
