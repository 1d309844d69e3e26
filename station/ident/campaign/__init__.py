"""One transducer, several top masses, identified jointly (a multi-mass campaign).

``identify`` (``identify_campaign``: the flow, its policy and refusal), ``jointfit`` (the joint
weighted least squares of Eq. 9 over the recordings), ``checks`` (end-mass separation, same
transducer, the campaign's uncertainty budget) and ``result`` (``CampaignResult`` and its JSON).
"""
