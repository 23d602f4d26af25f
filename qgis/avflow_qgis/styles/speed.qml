<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="Symbology">
  <pipe>
    <provider><resampling enabled="false" zoomedInResamplingMethod="nearestNeighbour" zoomedOutResamplingMethod="nearestNeighbour" maxOversampling="2"/></provider>
    <rasterrenderer type="singlebandpseudocolor" band="1" opacity="0.85" alphaBand="-1" classificationMin="0" classificationMax="50" nodataColor="">
      <rasterTransparency/>
      <minMaxOrigin><limits>None</limits><extent>WholeRaster</extent><statAccuracy>Estimated</statAccuracy><cumulativeCutLower>0.02</cumulativeCutLower><cumulativeCutUpper>0.98</cumulativeCutUpper><stdDevFactor>2</stdDevFactor></minMaxOrigin>
      <rastershader>
        <colorrampshader colorRampType="DISCRETE" classificationMode="3" clip="0" minimumValue="0" maximumValue="50" labelPrecision="2">
          <item alpha="0" value="1.0" label="&lt; 1 m/s" color="#ffffff"/>
          <item alpha="255" value="5.0" label="1–5 m/s" color="#fed976"/>
          <item alpha="255" value="10.0" label="5–10 m/s" color="#feb24c"/>
          <item alpha="255" value="20.0" label="10–20 m/s" color="#fd8d3c"/>
          <item alpha="255" value="30.0" label="20–30 m/s" color="#fc4e2a"/>
          <item alpha="255" value="40.0" label="30–40 m/s" color="#e31a1c"/>
          <item alpha="255" value="50.0" label="40–50 m/s" color="#bd0026"/>
          <item alpha="255" value="inf" label="≥ 50 m/s" color="#800026"/>
        </colorrampshader>
      </rastershader>
    </rasterrenderer>
    <brightnesscontrast brightness="0" contrast="0" gamma="1"/>
    <huesaturation saturation="0" grayscaleMode="0" colorizeOn="0" colorizeRed="255" colorizeGreen="128" colorizeBlue="128" colorizeStrength="100"/>
    <rasterresampler maxOversampling="2"/>
  </pipe>
  <blendMode>0</blendMode>
</qgis>
