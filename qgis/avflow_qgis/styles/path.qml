<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="Symbology">
  <renderer-v2 type="singleSymbol" symbollevels="0" enableorderby="0" forceraster="0">
    <symbols>
      <symbol name="0" type="line" alpha="1" clip_to_extent="1" force_rhr="0">
        <layer class="SimpleLine" enabled="1" locked="0" pass="0"><Option type="Map">
          <Option name="line_color" value="30,30,30,255" type="QString"/><Option name="line_style" value="dash" type="QString"/>
          <Option name="line_width" value="0.5" type="QString"/><Option name="line_width_unit" value="MM" type="QString"/></Option></layer>
      </symbol>
    </symbols>
  </renderer-v2>
</qgis>
