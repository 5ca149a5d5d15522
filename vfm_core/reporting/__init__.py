"""HTML reports of the study, the diagnosis and the drift test.

``page`` is the shared machinery (Jinja2 environment with autoescape, layout, figures,
number filters, atomic write); ``study``, ``diagnosis`` and ``drift`` each own one report:
they shape numbers and draw figures, and their template in ``templates/`` lays them out.
"""
