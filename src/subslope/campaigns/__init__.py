"""Commands over whole campaigns rather than one stage of one: the shard cache that
campaigns share (:mod:`.cache`) and the campaign run once per simulator variant
(:mod:`.systematics`)."""
