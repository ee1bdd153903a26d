# Stage: domain. Does the simulation look like the data? The Sérsic fits of the HST lens
# light (and the lens-light prior that covers them), and the summary statistics of the
# first domain.n_images images of domain.scene beside those of the 13 HST cutouts
# (subslope.stages.domain).


rule fit_lens_light:
    input:
        hst=observation_inputs(),
        psf=data_inputs("psf/"),
    output:
        csv=update("results/fit_lens_light/lens_light_fits.csv"),
        prior=update("results/fit_lens_light/lens_light_prior.yaml"),
    log:
        "logs/fit_lens_light.log",
    benchmark:
        "results/benchmarks/fit_lens_light.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        folder=lambda wildcards, input: observation_source(input.hst),
        # the values the fits depend on: a change reruns the job
        depends=lambda wildcards: {
            "instrument": config["instrument"],
            "lens_centre": config["hst"]["lens_centre"],
        },
    script:
        "../scripts/fit_lens_light.py"


rule check_domain:
    input:
        shards=lambda wildcards: domain_shards(),
        whitening=rules.compute_whitening.output.json,
        hst=observation_inputs(),
        psf=data_inputs("psf/"),
        cosmos=cosmos_files(),
    output:
        csv=update("results/check_domain/domain_check.csv"),
        statistics=update("results/check_domain/statistics.csv"),
        spread=update("results/check_domain/spread.csv"),
        sources=update("results/check_domain/sources.csv"),
        pdf=update("results/figures/domain_check.pdf"),
        png=update(
            report(
                "results/figures/domain_check.png",
                caption="../report/domain_check.rst",
                category="Simulation",
            )
        ),
        gallery_pdf=update("results/figures/domain_gallery.pdf"),
        gallery_png=update(
            report(
                "results/figures/domain_gallery.png",
                caption="../report/domain_gallery.rst",
                category="Simulation",
            )
        ),
        sources_pdf=update("results/figures/source_cleaning.pdf"),
        sources_png=update(
            report(
                "results/figures/source_cleaning.png",
                caption="../report/source_cleaning.rst",
                category="Simulation",
            )
        ),
    log:
        "logs/check_domain.log",
    benchmark:
        "results/benchmarks/check_domain.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=60,
    params:
        folder=lambda wildcards, input: observation_source(input.hst),
        scene=config["domain"]["scene"],
        n_images=config["domain"]["n_images"],
        # the values the statistics depend on: a change reruns the job
        depends=lambda wildcards: {
            "domain": config["domain"],
            "instrument": config["instrument"],
            "lens_centre": config["hst"]["lens_centre"],
            "mask_factor": config["training"]["mask_factor"],
            "inputs": config["training"]["inputs"],
            "sources": config["simulation"]["sources"],
        },
    script:
        "../scripts/check_domain.py"
