# Stage: data (always on). Materialise the checksummed real data (HST cutouts and their
# catalogue, empirical PSF, COSMOS sources) under config["data"]["resources_dir"], one
# job per registered file: a deleted or corrupted file is fetched again alone, and a
# mirror that lacks one file fails that job only.
# The data source (config["data"]["mirror"], ["allow_download"]) is read by the script
# from the config, not passed as params: files are identified by their checksums, so
# moving the mirror must not make Snakemake fetch (and first delete) them again. For the
# same reason a fetched file gets a fixed time stamp (subslope.io.resources): fetching
# the same bytes again never makes the jobs that read it run again.


# Runs on the submitting host: compute nodes of a cluster often have no network.
localrules:
    fetch_data,


rule fetch_data:
    output:
        update(f"{RESOURCES}/{{resource}}"),
    log:
        "logs/fetch_data/{resource}.log",
    wildcard_constraints:
        resource="|".join(re.escape(entry.path) for entry in REGISTRY),
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/fetch_data.py"
