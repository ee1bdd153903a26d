# Stage: data (always on). Materialise the checksummed real data (HST cutouts and their
# catalogue, empirical PSF, COSMOS sources) under config["data"]["resources_dir"].
# The data source (config["data"]["mirror"], ["allow_download"]) is read by the script
# from the config, not passed as params: files are identified by their checksums, so
# moving the mirror must not make Snakemake fetch (and first delete) them again.


# Runs on the submitting host: compute nodes of a cluster often have no network.
localrules:
    fetch_data,


rule fetch_data:
    output:
        hst=resource_files("hst/"),
        psf=resource_files("psf/"),
        cosmos=resource_files("cosmos/"),
        cosmos_extension=resource_files("cosmos_extension/"),
    log:
        "logs/fetch_data.log",
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/fetch_data.py"
