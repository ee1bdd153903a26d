# Stage: gallery. The 13 HST cutouts side by side (subslope.stages.gallery).


rule plot_hst_gallery:
    input:
        hst=observation_inputs(),
    output:
        pdf=update("results/figures/hst_gallery.pdf"),
        png=update(
            report(
                "results/figures/hst_gallery.png",
                caption="../report/hst_gallery.rst",
                category="Data",
            )
        ),
    log:
        "logs/plot_hst_gallery.log",
    conda:
        "../envs/subslope.yaml"
    params:
        folder=lambda wildcards, input: observation_source(input.hst),
        run_name=config["run_name"],
        pixel_scale=config["instrument"]["pixel_scale"],
    script:
        "../scripts/plot_hst_gallery.py"
